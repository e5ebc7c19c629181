"""Will the run fit? The disk checked before round 1 (zk0.disk), and what keep-checkpoints bounds."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess

import pytest

from zk0.config import RunConfig
from zk0.disk import GB, PER_ROUND_BYTES, bytes_needed, check_room, checkpoint_bytes, checkpoints_on_disk, size
from zk0.errors import Zk0Error

FULL_SIZE = 1.8e9  # a full-size SmolVLA checkpoint (docs/performance.md)


def test_a_long_full_size_run_stays_under_ten_gigabytes_at_the_default():
    """The issue's figure: 250 rounds, a checkpoint every 5: 50 checkpoints (90 GB) kept before;
    at keep-checkpoints' default at most three on disk at once, models/best besides."""
    long = RunConfig(num_server_rounds=250, checkpoint_interval=5)
    assert long.keep_checkpoints == 2 and checkpoints_on_disk(long, 1) == 3
    assert bytes_needed(long, 1, int(FULL_SIZE)) == 4 * int(FULL_SIZE) + 250 * PER_ROUND_BYTES
    assert bytes_needed(long, 1, int(FULL_SIZE)) < 10 * GB
    every = RunConfig(num_server_rounds=250, checkpoint_interval=5, keep_checkpoints=0)
    assert checkpoints_on_disk(every, 1) == 50 and bytes_needed(every, 1, int(FULL_SIZE)) > 90 * GB
    assert checkpoints_on_disk(every, 241) == 2  # resumed after round 240: rounds 245 and 250 are left
    assert checkpoints_on_disk(RunConfig(num_server_rounds=1), 1) == 1


def test_the_estimate_holds_a_checkpoint_as_written(tmp_path, client_parts):
    from zk0.artifacts import save_checkpoint

    bundle = client_parts[0]
    trainable = {name: p.detach().numpy() for name, p in bundle.policy.named_parameters() if p.requires_grad}
    folder = save_checkpoint(bundle, tmp_path, 1, {}, server_state=("nesterov", trainable))
    written = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    assert written <= checkpoint_bytes(bundle) < 1.5 * written


def test_sizes_read_as_a_person_would_say_them():
    assert [size(n) for n in (2 * 2**20, 21_000_000, int(FULL_SIZE), 90 * 10**9)] == [
        "2 MB",
        "21 MB",
        "1.8 GB",
        "90.0 GB",
    ]


def test_a_run_that_cannot_fit_is_refused_in_one_sentence_and_a_tight_one_warned(tmp_path, caplog):
    free = shutil.disk_usage(tmp_path).free
    with pytest.raises(Zk0Error) as refused:
        check_room(tmp_path, free + 10 * 2**30)
    sentence = str(refused.value)
    assert sentence.startswith(f"{str(tmp_path)!r} needs about ") and " is free there; " in sentence
    assert sentence.endswith("or lower keep-checkpoints.") and "\n" not in sentence

    from loguru import logger

    warnings = []
    sink = logger.add(warnings.append, level=logging.WARNING)
    try:
        check_room(tmp_path, int(0.95 * shutil.disk_usage(tmp_path).free))
        assert len(warnings) == 1 and "the disk will be nearly full" in warnings[0]
        check_room(tmp_path, 2**20)
        assert len(warnings) == 1
    finally:
        logger.remove(sink)


@pytest.mark.e2e
def test_a_federation_whose_output_folder_is_too_small_is_refused_before_round_1(tmp_path):
    """The real `flwr run` with output-dir on a 2 MB filesystem (tmpfs): one sentence naming the
    folder, what the run needs and what is free; no round, no traceback."""
    from zk0.simulation import cpu_federation, flwr_run, local_federation

    if os.geteuid() != 0:
        pytest.skip("mounting a small filesystem (tmpfs) needs root")
    small = tmp_path / "small"
    small.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(small)], check=True)
    try:
        with local_federation(tmp_path / "flwr-home") as env:
            log = flwr_run(env, f"output-dir='{small}'", cpu_federation(2, actors=1))
        (run_dir,) = small.iterdir()
    finally:
        subprocess.run(["umount", "--lazy", str(small)], check=False)
    sentence = f"zk0: {str(run_dir)!r} needs about "
    assert log.count(sentence) == 1 and "but only 2 MB is free there; free some space" in log, log[-4000:]
    assert "Exit Code: " in log and "Round 1" not in log and "Traceback" not in log, log[-4000:]
