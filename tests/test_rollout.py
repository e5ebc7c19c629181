"""A zk0 checkpoint runs on an SO-101 the way docs/robot-owners.md says: with ``lerobot-rollout``.

lerobot 0.6 removed ``lerobot-record --policy.path``; its replacement, ``lerobot-rollout``
(lerobot/scripts/lerobot_rollout.py), parses ``RolloutConfig`` with ``lerobot.configs.parser.wrap``
(``RolloutConfig.__post_init__`` reads the policy config from ``--policy.path``) and then
``lerobot.rollout.build_rollout_context`` loads the weights, makes the processors with
``make_pre_post_processors(pretrained_path=..., preprocessor_overrides={device, rename_map})``, and
wires them to the robot and a ``SyncInferenceEngine``. These tests run that code on a checkpoint
written by ``zk0.artifacts.run_folder.save_checkpoint``, with one substitution: the SO-101 follower keeps its
real joint and camera features but its motor bus and cameras are a fixed synthetic scene.

No ``from __future__ import annotations`` here: ``parser.wrap`` reads the config class from the
wrapped function's annotation, which must be the class, not a string.
"""

import json
import shutil
import sys
from threading import Event
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("lerobot.rollout")

import lerobot.rollout.context as rollout_context  # noqa: E402
import lerobot.scripts.lerobot_rollout  # noqa: E402, F401  (registers the robot and camera types, as the CLI does)
from lerobot.cameras.utils import make_cameras_from_configs  # noqa: E402
from lerobot.configs import parser  # noqa: E402
from lerobot.processor import NormalizerProcessorStep, PolicyProcessorPipeline, UnnormalizerProcessorStep  # noqa: E402
from lerobot.robots import Robot  # noqa: E402
from lerobot.robots.so_follower import SO101Follower, SO101FollowerConfig  # noqa: E402
from lerobot.rollout import RolloutConfig, RTCInferenceEngine, build_rollout_context, create_strategy  # noqa: E402

TASK = "Pick up the cube and place it in the box."
HEIGHT, WIDTH = 48, 64  # the synthetic datasets' frames
JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]  # SOFollower's motors


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A zk0 checkpoint directory (the tiny policy on client 0's dataset) and the bundle it was written from.

    Its processors carry client 0's statistics; ``client_stats/`` holds client 0's and client 1's.
    """
    from lerobot.processor import rename_stats

    from zk0.artifacts.run_folder import save_checkpoint
    from zk0.config import from_run_config
    from zk0.data.loaders import open_metadata
    from zk0.data.registry import load_registry
    from zk0.federation.client import build_client

    registry = load_registry()
    client = build_client(from_run_config({"batch-size": 4}), registry.clients[0], registry.model_cameras())
    bundle = client.bundle
    other = registry.clients[1]
    client_stats = {
        "client_0_synth-so100-pickplace": bundle.stats,
        f"client_1_{other.name}": rename_stats(open_metadata(other).stats, other.rename_map()),
    }
    path = save_checkpoint(bundle, tmp_path_factory.mktemp("run"), 3, client_stats)
    return path, bundle


class SyntheticSO101(SO101Follower):
    """An SO-101 follower whose bus and cameras are a fixed scene; it records the actions it is sent.

    Its features are SO101Follower's own (``<motor>.pos`` per motor, one (H, W, 3) frame per
    camera from the camera configs); only the Feetech bus, whose SDK is the robot machine's
    ``lerobot[feetech]`` extra, is replaced by the motor names SOFollower gives it.
    """

    def __init__(self, config, scene: dict):
        Robot.__init__(self, config)  # id and calibration folder, as SOFollower.__init__ starts
        self.config = config
        self.bus = SimpleNamespace(motors=dict.fromkeys(JOINTS))
        self.cameras = make_cameras_from_configs(config.cameras)  # built, never opened
        self.scene = scene
        self.sent: list[dict] = []
        self.stop_after: tuple[int, Event] | None = None
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    def get_observation(self) -> dict:
        return {key: value.copy() if isinstance(value, np.ndarray) else value for key, value in self.scene.items()}

    def send_action(self, action: dict) -> dict:
        self.sent.append(dict(action))
        if self.stop_after and len(self.sent) >= self.stop_after[0]:
            self.stop_after[1].set()
        return action


def scene(bundle, cameras: list[str]) -> dict:
    """Joints at the dataset's mean state and one random frame per camera, as SO101Follower reports them."""
    state = np.asarray(bundle.stats["observation.state"]["mean"], dtype=np.float32).reshape(-1)
    joints = {f"{motor}.pos": float(value) for motor, value in zip(JOINTS, state, strict=True)}
    frames = np.random.default_rng(0).integers(0, 256, (len(cameras), HEIGHT, WIDTH, 3), dtype=np.uint8)
    return {**joints, **dict(zip(cameras, frames, strict=True))}


def rollout_args(checkpoint_dir, calibration_dir, cameras: list[str], *extra: str) -> list[str]:
    """The command line of docs/robot-owners.md, with cameras at the synthetic frames' size."""
    specs = ", ".join(
        f"{name}: {{type: opencv, index_or_path: {i}, width: {WIDTH}, height: {HEIGHT}, fps: 30}}"
        for i, name in enumerate(cameras)
    )
    return [
        "--strategy.type=base",
        f"--policy.path={checkpoint_dir}",
        "--robot.type=so101_follower",
        "--robot.port=/dev/ttyACM0",
        "--robot.id=my_arm",
        f"--robot.calibration_dir={calibration_dir}",
        f"--robot.cameras={{ {specs} }}",
        f"--task={TASK}",
        "--duration=60",
        "--return_to_initial_position=false",
        *extra,
    ]


def parse_like_rollout(monkeypatch, args: list[str]) -> RolloutConfig:
    """``lerobot-rollout``'s own parsing: ``parser.wrap`` over ``RolloutConfig`` reading ``sys.argv``."""

    @parser.wrap()
    def parsed(cfg: RolloutConfig) -> RolloutConfig:
        return cfg

    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", *args])
    return parsed()


def connect_synthetic_robot(monkeypatch, scene_values: dict) -> None:
    """The one hardware seam: the robot ``build_rollout_context`` makes from ``--robot.*``.

    ``make_robot_from_config`` is the name ``lerobot.rollout.context`` imported; replacing it there
    keeps the real SO-101 config, features and name while nothing opens a serial port or camera.
    """
    monkeypatch.setattr(rollout_context, "make_robot_from_config", lambda config: SyntheticSO101(config, scene_values))


def predict_chunk(policy, preprocessor, postprocessor, scene_values: dict, cameras, seed: int) -> torch.Tensor:
    """One action chunk in joint units from ``scene_values``; ``cameras`` pairs model camera names with the robot's."""
    batch = {
        f"observation.images.{name}": torch.from_numpy(scene_values[src]).permute(2, 0, 1).float().div(255)[None]
        for name, src in cameras
    }
    state = [scene_values[f"{motor}.pos"] for motor in JOINTS]
    batch |= {"observation.state": torch.tensor([state]), "task": TASK, "robot_type": "so101_follower"}
    policy.reset()
    policy.eval()
    torch.manual_seed(seed)
    with torch.inference_mode():
        return postprocessor(policy.predict_action_chunk(preprocessor(batch))).cpu()


def trained_chunk(bundle, scene_values: dict, cameras, seed: int) -> torch.Tensor:
    """The chunk of the in-memory policy and processors the checkpoint was written from."""
    return predict_chunk(bundle.policy, bundle.preprocessor, bundle.postprocessor, scene_values, cameras, seed)


def run_ticks(ctx, ticks: int, seed: int) -> list[dict]:
    """lerobot-rollout's base strategy (setup, control loop, teardown) until the robot got ``ticks`` actions."""
    robot = ctx.hardware.robot_wrapper.inner
    robot.stop_after = (ticks, ctx.runtime.shutdown_event)
    strategy = create_strategy(ctx.runtime.cfg.strategy)
    strategy.setup(ctx)
    torch.manual_seed(seed)  # SmolVLA samples its flow-matching noise from torch's generator
    try:
        strategy.run(ctx)
    finally:
        strategy.teardown(ctx)
    assert not robot.is_connected, "teardown disconnects the robot"
    return robot.sent


def test_lerobot_rollout_drives_an_so101_with_a_zk0_checkpoint(checkpoint, tmp_path, monkeypatch):
    path, bundle = checkpoint
    cameras = ["camera1", "camera2"]  # named as in training: no --rename_map needed
    cfg = parse_like_rollout(monkeypatch, rollout_args(path, tmp_path, cameras))

    # RolloutConfig.__post_init__ read the checkpoint's policy config from --policy.path.
    assert cfg.policy.type == "smolvla"
    assert str(cfg.policy.pretrained_path) == str(path)
    # (lerobot registers one config class as so100_follower and so101_follower; its .type reads so100_follower)
    assert isinstance(cfg.robot, SO101FollowerConfig) and cfg.robot.port == "/dev/ttyACM0"
    assert cfg.robot.id == "my_arm" and sorted(cfg.robot.cameras) == cameras
    assert cfg.device == bundle.device.type, "the device comes from the checkpoint's config"
    assert cfg.task == TASK and cfg.strategy.type == "base"

    values = scene(bundle, cameras)
    connect_synthetic_robot(monkeypatch, values)
    ctx = build_rollout_context(cfg, Event())
    policy = ctx.policy.policy
    assert not policy.training
    assert ctx.data.ordered_action_keys == [f"{motor}.pos" for motor in JOINTS]
    trained = bundle.policy.state_dict()
    assert policy.state_dict().keys() == trained.keys()
    for name, loaded in policy.state_dict().items():
        torch.testing.assert_close(loaded, trained[name], rtol=0, atol=0, msg=name)

    # The loaded policy and processors predict the trained policy's chunk, in joint units.
    pairs = [(c, c) for c in cameras]
    expected = trained_chunk(bundle, values, pairs, seed=0)
    chunk = predict_chunk(policy, ctx.policy.preprocessor, ctx.policy.postprocessor, values, pairs, seed=0)
    assert chunk.shape == expected.shape == (1, policy.config.chunk_size, len(JOINTS))
    assert torch.isfinite(chunk).all()
    torch.testing.assert_close(chunk, expected, rtol=1e-4, atol=1e-3)

    # lerobot-rollout's control loop sends the robot that chunk, one action per tick, then a fresh one.
    n_steps = policy.config.n_action_steps
    ticks = n_steps + 2
    sent = run_ticks(ctx, ticks, seed=0)
    assert len(sent) == ticks
    assert all(list(action) == [f"{motor}.pos" for motor in JOINTS] for action in sent)
    actions = torch.tensor([[action[f"{motor}.pos"] for motor in JOINTS] for action in sent])
    assert torch.isfinite(actions).all()
    torch.testing.assert_close(actions[:n_steps], expected[0, :n_steps].float(), rtol=1e-4, atol=1e-3)
    # Unnormalised with the checkpoint's statistics: actions sit near the dataset's action range.
    low = torch.as_tensor(np.asarray(bundle.stats["action"]["min"]), dtype=torch.float32)
    high = torch.as_tensor(np.asarray(bundle.stats["action"]["max"]), dtype=torch.float32)
    span = high - low
    assert ((actions > low - 10 * span) & (actions < high + 10 * span)).all(), actions


def test_cameras_with_other_names_need_the_rename_map(checkpoint, tmp_path, monkeypatch):
    path, bundle = checkpoint
    cameras = ["front", "wrist"]
    values = scene(bundle, cameras)
    connect_synthetic_robot(monkeypatch, values)

    cfg = parse_like_rollout(monkeypatch, rollout_args(path, tmp_path, cameras))
    with pytest.raises(ValueError, match="Visual feature mismatch"):
        build_rollout_context(cfg, Event())

    rename = '{"observation.images.front": "observation.images.camera1", "observation.images.wrist": "observation.images.camera2"}'
    cfg = parse_like_rollout(monkeypatch, rollout_args(path, tmp_path, cameras, f"--rename_map={rename}"))
    assert cfg.rename_map == {
        "observation.images.front": "observation.images.camera1",
        "observation.images.wrist": "observation.images.camera2",
    }
    ctx = build_rollout_context(cfg, Event())
    sent = run_ticks(ctx, 1, seed=1)
    got = torch.tensor([[sent[0][f"{motor}.pos"] for motor in JOINTS]])
    expected = trained_chunk(bundle, values, [("camera1", "front"), ("camera2", "wrist")], seed=1)
    torch.testing.assert_close(got, expected[0, :1].float(), rtol=1e-4, atol=1e-3)


def test_real_time_chunking_runs_a_zk0_checkpoint(checkpoint, tmp_path, monkeypatch):
    """``--inference.type=rtc`` (docs/robot-owners.md): SmolVLA's chunks computed in a background thread."""
    path, bundle = checkpoint
    cameras = ["camera1", "camera2"]
    connect_synthetic_robot(monkeypatch, scene(bundle, cameras))
    # 2 Hz, 5 actions: lerobot's RTC thread plans again as soon as it is done (its queue threshold,
    # 30, is above the tiny policy's 10-action chunk), and drops from each new chunk the actions that
    # went by while it was computed. On an idle CPU a chunk takes about 0.5 s; on a CI machine running
    # other tests the control loop once got only 7 actions in 60 s at 5 Hz.
    cfg = parse_like_rollout(monkeypatch, rollout_args(path, tmp_path, cameras, "--inference.type=rtc", "--fps=2"))
    ctx = build_rollout_context(cfg, Event())
    assert isinstance(ctx.policy.inference, RTCInferenceEngine)
    sent = run_ticks(ctx, 5, seed=0)
    actions = torch.tensor([[action[f"{motor}.pos"] for motor in JOINTS] for action in sent])
    assert actions.shape == (5, len(JOINTS)) and torch.isfinite(actions).all()


def test_a_robot_owner_can_roll_out_with_their_own_statistics(checkpoint, tmp_path, monkeypatch):
    """docs/robot-owners.md's recipe: a copy of the checkpoint whose processors carry client_stats/<client>.json.

    lerobot-rollout passes no statistics of its own to ``make_pre_post_processors`` (with a
    ``pretrained_path`` it ignores ``dataset_stats``): it normalises with what the checkpoint's
    processors saved.
    """
    path, bundle = checkpoint
    own = next((path / "client_stats").glob("client_1_*.json"))
    # The doc's snippet, with its placeholders filled in.
    ckpt = path
    mine = ckpt.with_name(ckpt.name + "_mine")
    shutil.copytree(ckpt, mine)
    stats = json.loads((ckpt / "client_stats" / own.name).read_text())
    for name, step in (
        ("policy_preprocessor", "normalizer_processor"),
        ("policy_postprocessor", "unnormalizer_processor"),
    ):
        pipeline = PolicyProcessorPipeline.from_pretrained(mine, f"{name}.json", overrides={step: {"stats": stats}})
        pipeline.save_pretrained(mine)

    cameras = ["camera1", "camera2"]
    connect_synthetic_robot(monkeypatch, scene(bundle, cameras))
    ctx = build_rollout_context(parse_like_rollout(monkeypatch, rollout_args(mine, tmp_path, cameras)), Event())
    for pipeline, kind in (
        (ctx.policy.preprocessor, NormalizerProcessorStep),
        (ctx.policy.postprocessor, UnnormalizerProcessorStep),
    ):
        (step,) = [s for s in pipeline.steps if type(s) is kind]
        for key in ("observation.state", "action"):
            # _tensor_stats is private to lerobot's (un)normalizer: the statistics it applies.
            mean = step._tensor_stats[key]["mean"].cpu().double()
            assert torch.allclose(mean, torch.tensor(stats[key]["mean"], dtype=torch.float64), atol=1e-5), key
            assert not torch.allclose(mean, torch.as_tensor(np.asarray(bundle.stats[key]["mean"])).double()), key
    sent = run_ticks(ctx, 1, seed=0)
    assert torch.isfinite(torch.tensor([sent[0][f"{motor}.pos"] for motor in JOINTS])).all()
