"""Will the run fit? The disk checked before round 1 (zk0.artifacts.disk), and what keep-checkpoints bounds."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import subprocess

import pytest

from zk0.artifacts.disk import (
    GB,
    PER_ROUND_BYTES,
    bytes_needed,
    check_room,
    checkpoint_bytes,
    checkpoints_on_disk,
    full_disk_in_one_sentence,
    is_full,
    size,
)
from zk0.common.errors import Zk0Error
from zk0.config import RunConfig

FULL_SIZE = 1.8e9  # a full-size SmolVLA checkpoint (docs/performance.md)


@contextlib.contextmanager
def small_disk(folder, megabytes: float):
    """A filesystem of its own at ``folder`` (tmpfs), ``megabytes`` big: a disk the test can fill."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small filesystem (tmpfs) needs root")
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={int(megabytes * 1024)}k", "tmpfs", str(folder)], check=True)
    try:
        yield folder
    finally:
        subprocess.run(["umount", "--lazy", str(folder)], check=False)


def fill(folder, leave: int = 0) -> None:
    """Write a file in ``folder`` that leaves at most ``leave`` bytes of its filesystem free."""
    with open(folder / "filler", "wb", buffering=0) as out:
        # All but the last megabyte at once where the filesystem can (tmpfs can): a run must not
        # outpace the filling. The writes below take the rest, to the block.
        with contextlib.suppress(OSError):
            os.posix_fallocate(out.fileno(), 0, shutil.disk_usage(folder).free - leave - 2**20)
        out.seek(0, os.SEEK_END)
        while (free := shutil.disk_usage(folder).free - leave) > 0:
            try:
                out.write(b"\0" * min(free, 2**20))
            except OSError:  # full: the filesystem's own accounting rounds to its blocks
                break


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
    from zk0.artifacts.run_folder import save_checkpoint

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


def test_a_full_disk_leaves_no_half_file_and_reads_as_one_sentence(tmp_path):
    """On a real full filesystem: zk0's writes leave neither the file nor a temporary one; the
    errors Python and safetensors raise are both recognised and read as one sentence."""
    import torch
    from safetensors.torch import save_file

    from zk0.artifacts.run_folder import write_json

    with small_disk(tmp_path / "disk", 1) as disk:
        fill(disk, leave=4096)
        with pytest.raises(OSError) as python:
            write_json(disk / "server" / "round_3.json", {"x": "y" * 100_000})
        assert is_full(python.value)
        assert sorted(p.name for p in disk.rglob("*")) == ["filler", "server"]
        with pytest.raises(Exception) as wrapped:  # safetensors' SafetensorError: "... os error 28"
            save_file({"w": torch.zeros(100_000)}, disk / "state.safetensors")
        assert not isinstance(wrapped.value, OSError) and is_full(wrapped.value)
        assert not is_full(OSError(13, "Permission denied")) and not is_full(ValueError("no space"))
        with pytest.raises(Zk0Error) as said, full_disk_in_one_sentence(tmp_path, "free some space there."):
            write_json(disk / "server" / "round_3.json", {"x": "y" * 100_000})
        assert (
            str(said.value) == f"The disk holding {str(disk / 'server')!r} is full (0 MB free); free some space there."
        )


@pytest.mark.allowance(240)
@pytest.mark.e2e
def test_a_disk_too_small_is_refused_before_round_1_and_one_that_fills_mid_run_stops_it_in_one_sentence(
    flower_env, tmp_path
):
    """The real `flwr run` with output-dir on a filesystem of its own (tmpfs). At 2 MB: refused before
    round 1 in one sentence naming the folder, what the run needs and what is free. Made 512 MB and
    filled by another program once round 1's checkpoint is written: the run stops with zk0's
    sentence naming that disk, no traceback, no partial file; freed, `resume-from` finishes it (that
    a resumed run equals one never interrupted, bit for bit, test_federation checks)."""
    import threading
    import time

    from safetensors.torch import load_file

    from zk0.deployment.simulation import cpu_federation, flwr_run

    config = "num-server-rounds=3 local-steps=2 batch-size=4 checkpoint-interval=1 eval-batches=1"
    env = flower_env
    with small_disk(tmp_path / "disk", 2) as disk:
        log = flwr_run(env, f"{config} output-dir='{disk}'", cpu_federation(2, actors=1))
        (refused,) = disk.iterdir()
        assert log.count(f"zk0: {str(refused)!r} needs about ") == 1, log[-4000:]
        assert "but only 2 MB is free there; free some space" in log and "Exit Code: " in log, log[-4000:]
        assert "Round 1" not in log and "Traceback" not in log, log[-4000:]
        shutil.rmtree(refused)

        subprocess.run(["mount", "-o", "remount,size=512m", str(disk)], check=True)

        def fill_after_round_1() -> None:
            deadline = time.monotonic() + 600
            while not list(disk.glob("*/models/checkpoint_round_1")) and time.monotonic() < deadline:
                time.sleep(0.05)
            fill(disk)

        filler = threading.Thread(target=fill_after_round_1)
        filler.start()
        log = flwr_run(env, f"{config} output-dir='{disk}'", cpu_federation(2, actors=1))
        filler.join()
        (run_dir,) = [p for p in disk.iterdir() if p.is_dir()]
        assert "is full (0 MB free); " in log and "Exit Code: " in log, log[-4000:]
        assert "Traceback" not in log and "Done in" not in log, log[-4000:]
        assert not [p for p in run_dir.rglob("*") if p.name.startswith(".") or "partial" in p.name]

        (disk / "filler").unlink()
        log = flwr_run(env, f"{config} output-dir='{disk}' resume-from='{run_dir}'", cpu_federation(2, actors=1))
        assert "Done in" in log, log[-4000:]
        assert load_file(run_dir / "models" / "checkpoint_round_3" / "model.safetensors")
