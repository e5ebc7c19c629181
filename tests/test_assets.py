"""The offline assets: real LeRobotDatasets with decodable video, a tiny backbone, determinism."""

from __future__ import annotations

import hashlib
import os
import threading

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from transformers import AutoProcessor

from zk0.data.assets import AssetError, ensure_backbone, ensure_dataset, synthetic_dataset_root
from zk0.data.assets.datasets import COLOURS, JOINT_NAMES, NON_IID, SPECS, write_synthetic_dataset


@pytest.mark.parametrize(
    "name",
    [*sorted(name for name, spec in SPECS.items() if not spec.benchmark_only), "synth-owner-0", "synth-owner-63"],
)
def test_each_synthetic_dataset_opens_and_decodes_a_frame(name):
    spec = SPECS[name]
    root = ensure_dataset(name)
    dataset = LeRobotDataset(spec.repo_id, root=root)
    assert dataset.num_episodes == spec.episodes
    assert dataset.num_frames == spec.episodes * spec.frames_per_episode
    assert dataset.meta.robot_type == spec.robot_type
    assert dataset.meta.features["observation.state"]["names"] == list(JOINT_NAMES)
    item = dataset[spec.frames_per_episode + 3]
    for camera in spec.cameras:
        frame = item[f"observation.images.{camera}"]
        assert frame.shape == (3, spec.height, spec.width)
        assert frame.std() > 0.01  # a real picture, not a blank
    colour = next(c for c in spec.colours if c in item["task"])
    target = torch.tensor(COLOURS[colour], dtype=torch.float32) / 255
    scene = item[f"observation.images.{spec.cameras[0]}"]
    distance = (scene - target[:, None, None]).abs().sum(dim=0)
    assert (distance < 0.35).sum() >= 4, "the target named in the task is visible in the scene camera"


def test_state_moves_toward_a_target_dependent_pose():
    spec = SPECS["synth-so100-pickplace"]
    dataset = LeRobotDataset(spec.repo_id, root=ensure_dataset(spec.name))
    states = torch.stack([dataset[i]["observation.state"] for i in range(spec.frames_per_episode)])
    actions = torch.stack([dataset[i]["action"] for i in range(spec.frames_per_episode)])
    torch.testing.assert_close(actions[:-1], states[1:])  # action = next commanded joint positions
    steps = (states[1:] - states[:-1]).norm(dim=1)
    assert steps[-3:].mean() < steps[:3].mean() / 3, "the arm settles on its target"


def test_generator_is_deterministic_in_its_seed(tmp_path):
    spec = SPECS["synth-so101-reach"]

    def parquet_digest(root):
        files = sorted((root / "data").rglob("*.parquet"))
        return hashlib.sha256(b"".join(f.read_bytes() for f in files)).hexdigest()

    a = write_synthetic_dataset(spec, tmp_path / "a", seed=7, episodes=2)
    b = write_synthetic_dataset(spec, tmp_path / "b", seed=7, episodes=2)
    c = write_synthetic_dataset(spec, tmp_path / "c", seed=8, episodes=2)
    assert parquet_digest(a) == parquet_digest(b)
    assert parquet_digest(a) != parquet_digest(c)


def test_tiny_backbone_builds_a_small_smolvla(registry):
    from zk0.config import RunConfig
    from zk0.data.loaders import open_metadata
    from zk0.learning.policy import build_policy

    processor = AutoProcessor.from_pretrained(ensure_backbone())
    assert processor.tokenizer.fake_image_token_id != processor.tokenizer.unk_token_id
    entry = registry.clients[0]
    bundle = build_policy(RunConfig(), open_metadata(entry), entry, registry.model_cameras())
    total = sum(p.numel() for p in bundle.policy.parameters())
    assert type(bundle.policy).__name__ == "SmolVLAPolicy"
    assert total < 1_000_000


@pytest.mark.parametrize(("model", "tokens"), [("tiny", 4), ("tiny-128", 64)])
def test_each_offline_model_sees_a_camera_as_so_many_visual_tokens(registry, model, tokens):
    """The 64 px tiny model sees a camera as 4 tokens (a 3 cm cube is about 3 of its pixels); the
    simulator's tiny-128 model as 64, from 128 px frames in 8 px patches."""
    from zk0.config import RunConfig
    from zk0.data.loaders import open_metadata
    from zk0.learning.policy import build_policy

    entry = registry.clients[0]
    bundle = build_policy(RunConfig(model=model), open_metadata(entry), entry, registry.model_cameras())
    size = bundle.policy.config.resize_imgs_with_padding
    embedded = bundle.policy.model.vlm_with_expert.embed_image(torch.zeros(1, 3, *size))
    assert embedded.shape[:2] == (1, tokens)


def test_stale_asset_is_regenerated(tmp_path):
    first = ensure_dataset("synth-so100-eval", tmp_path, episodes=1)
    marker = first / "meta" / "info.json"
    assert LeRobotDataset("zk0/synth_so100_eval", root=first).num_episodes == 1
    ensure_dataset("synth-so100-eval", tmp_path, episodes=2)
    assert marker.exists()
    assert LeRobotDataset("zk0/synth_so100_eval", root=first).num_episodes == 2


def test_a_dataset_recorded_with_more_episodes_is_kept_by_a_run_that_asks_for_no_count(tmp_path):
    """``zk0 assets --episodes 8`` and then train.sh's asset step (no count): the 8 stay. A count
    asked for and different from what is there records it again, and says so in one sentence."""
    from loguru import logger

    ensure_dataset("synth-so100-eval", tmp_path, episodes=8)
    root = ensure_dataset("synth-so100-eval", tmp_path)
    assert LeRobotDataset("zk0/synth_so100_eval", root=root).num_episodes == 8
    messages = []
    sink = logger.add(lambda m: messages.append(m.record["message"]), level="WARNING")
    try:
        ensure_dataset("synth-so100-eval", tmp_path, episodes=7)
        ensure_dataset("synth-so100-eval", tmp_path, episodes=7)  # as it is now: nothing to say
    finally:
        logger.remove(sink)
    assert LeRobotDataset("zk0/synth_so100_eval", root=root).num_episodes == 7
    assert messages == ["Recording 'synth-so100-eval' again with 7 episodes in place of the 8 it has: 7 were asked for."]


@pytest.mark.parametrize(
    ("call", "needle"),
    [
        (lambda tmp: synthetic_dataset_root("synth-nope", tmp), "'synth-nope'"),
        (lambda tmp: ensure_dataset("synth-so100-eval", tmp, episodes=-3), "-3"),
        (lambda tmp: ensure_backbone(tmp / "file.txt" / "cache"), "not writable"),
    ],
)
def test_bad_asset_requests_fail_with_one_sentence(tmp_path, call, needle):
    (tmp_path / "file.txt").write_text("not a directory")
    with pytest.raises(AssetError) as err:
        call(tmp_path)
    message = str(err.value)
    assert needle in message and message.endswith(".") and "\n" not in message


def test_cli_assets_prints_paths_and_rejects_bad_names(tmp_path, capsys):
    from zk0.cli import main

    assert main(["assets", "--cache-dir", str(tmp_path), "--only", "tiny-smolvlm", "tiny-smolvlm-128"]) == 0
    printed = capsys.readouterr().out
    assert str(tmp_path / "backbones" / "tiny-smolvlm") in printed
    assert str(tmp_path / "backbones" / "tiny-smolvlm-128") in printed
    assert main(["assets", "--cache-dir", str(tmp_path), "--only", "synth-nope"]) == 2
    assert "'synth-nope'" in capsys.readouterr().err


@pytest.mark.slow  # a process of its own, which imports lerobot
def test_cli_assets_shows_one_bar_of_its_own_and_logs_what_the_libraries_print(tmp_path):
    """Generating prints zk0's progress bar, not FFmpeg's muxer lines or datasets' bars; those are in
    assets.log in the cache."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "zk0.cli", "assets", "--cache-dir", str(tmp_path), "--only", "synth-so101-reach"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert done.stdout.strip() == f"synth-so101-reach: {tmp_path / 'datasets' / 'zk0' / 'synth_so101_reach'}"
    assert "Offline assets: 100%" in done.stderr and "moov" not in done.stderr and "Map" not in done.stderr
    assert "moving the moov atom" in (tmp_path / "assets.log").read_text()


def scene_target(dataset: LeRobotDataset, index: int, spec) -> tuple[float, float]:
    """Where the task's target lies in the scene camera, as fractions of the image."""
    item = dataset[index]
    colour = next(c for c in spec.colours if c in item["task"])
    rgb = torch.tensor(COLOURS[colour], dtype=torch.float32) / 255
    scene = item[f"observation.images.{spec.cameras[0]}"]
    ys, xs = torch.nonzero((scene - rgb[:, None, None]).abs().sum(dim=0) < 0.35, as_tuple=True)
    return float(xs.float().mean()) / (spec.width - 1), float(ys.float().mean()) / (spec.height - 1)


@pytest.mark.parametrize("name", sorted(NON_IID))
def test_each_noniid_client_sees_its_own_quarter_and_moves_at_its_own_rate(name):
    spec = SPECS[name]
    dataset = LeRobotDataset(spec.repo_id, root=ensure_dataset(name))
    x0, x1, y0, y1 = spec.target_region
    slack = 0.05  # the target square's half-size
    for episode in range(spec.episodes):
        u, v = scene_target(dataset, episode * spec.frames_per_episode, spec)
        assert x0 - slack <= u <= x1 + slack and y0 - slack <= v <= y1 + slack, (episode, u, v)

    # action - state = rate * (goal - state) + noise, and the next state is the action: each step
    # covers (1 - rate) of the one before. Fitted over the first frames, where steps are large.
    states, actions = (np.stack(dataset.hf_dataset[key]) for key in ("observation.state", "action"))
    steps = (actions - states).reshape(spec.episodes, spec.frames_per_episode, -1)[:, :8]
    now, after = steps[:, :-1].reshape(-1), steps[:, 1:].reshape(-1)
    assert float(now @ after / (now @ now)) == pytest.approx(1 - spec.approach_rate, abs=0.02)


def test_many_owners_differ_within_the_server_sets_span_and_each_is_a_function_of_its_name():
    owners = [SPECS[f"synth-owner-{i}"] for i in range(64)]
    server = SPECS["synth-so100-eval"]
    X0, X1, Y0, Y1 = server.target_region
    for spec in owners:
        x0, x1, y0, y1 = spec.target_region
        assert X0 <= x0 < x1 <= X1 and Y0 <= y0 < y1 <= Y1, spec.name
        assert set(spec.colours) <= set(server.colours) and 2 <= len(spec.colours) <= 3
        assert spec.episodes >= 5 and 0.1 <= spec.approach_rate <= 0.3
    assert len({s.target_region for s in owners}) == 64 and len({s.approach_rate for s in owners}) == 64
    assert len({(s.robot_type, s.task_template, s.cameras) for s in owners}) == 4  # the four hand-written owners'
    assert SPECS["synth-owner-5"] == SPECS["synth-owner-5"] and SPECS["synth-owner-5"] != SPECS["synth-owner-6"]
    for name in ("synth-owner-07", "synth-owner-1000", "synth-owner-", "synth-owner-x"):
        assert name not in SPECS
    assert "synth-owner-7" not in list(SPECS)  # `zk0 assets` makes the hand-written ones by default


def test_noniid_quarters_are_disjoint_and_the_rates_average_to_the_server_sets():
    regions = [SPECS[n].target_region for n in NON_IID]
    for i, (a0, a1, b0, b1) in enumerate(regions):
        for c0, c1, d0, d1 in regions[i + 1 :]:
            assert a1 <= c0 or c1 <= a0 or b1 <= d0 or d1 <= b0
    rates = [SPECS[n].approach_rate for n in NON_IID]
    assert len(set(rates)) == len(rates)
    assert sum(rates) / len(rates) == pytest.approx(SPECS["synth-so100-eval"].approach_rate)


def policy_after(work) -> int:
    """The scheduling policy of a thread of its own once it has done ``work`` (this test's worker
    keeps its own, whatever ``work`` does)."""
    seen = []
    thread = threading.Thread(target=lambda: (work(), seen.append(os.sched_getscheduler(0))))
    thread.start()
    thread.join()
    return seen[0]


@pytest.mark.skipif(os.geteuid() != 0, reason="SVT-AV1 raises only root's threads to real-time priority")
def test_recording_leaves_the_thread_that_encoded_at_ordinary_priority(tmp_path):
    """As root, lerobot's video codec (libsvtav1) leaves the thread that opened an encoder at
    real-time SCHED_FIFO priority, which every process that thread starts inherits; each of zk0's
    recorders (the synthetic owners' and the simulator's) puts the thread back."""
    import av

    from zk0.sim.record import record_demonstrations
    from zk0.sim.tasks import SIM_SPECS

    def encode():
        with av.open(str(tmp_path / "raw.mp4"), "w") as container:
            stream = container.add_stream("libsvtav1", rate=30)
            stream.width, stream.height, stream.pix_fmt = 64, 64, "yuv420p"
            frame = av.VideoFrame.from_ndarray(np.zeros((64, 64, 3), np.uint8), format="rgb24")
            for packet in [*stream.encode(frame), *stream.encode()]:
                container.mux(packet)

    assert policy_after(encode) == os.SCHED_FIFO, "SVT-AV1 no longer does this: zk0.common.machine.ordinary_scheduling can go"
    spec = SPECS["synth-so101-reach"]
    assert policy_after(lambda: write_synthetic_dataset(spec, tmp_path / "synth", seed=7, episodes=1)) == os.SCHED_OTHER
    sim = SIM_SPECS["sim-so101-left"]
    assert policy_after(lambda: record_demonstrations(sim, tmp_path / "sim", seed=0, episodes=1)) == os.SCHED_OTHER
