"""Synthetic SO-100/SO-101 datasets written with lerobot's own dataset writer.

Each episode shows a coloured target somewhere on the table; the 6 joints move from a
noisy home pose toward a pose that depends on where the target is and which colour it
has, and the action is the next commanded joint position. The task text names the
target. A policy therefore has to look at the image (and read the task) to do better
than "predict the mean action" - which is what makes these datasets *learnable*.

The four client datasets differ the way community SO-100/SO-101 datasets differ
(task text, colours and where targets lie, camera names, image size, episode count,
fps); a fifth is held by the server for evaluation. Everything is a pure function of
the spec and the seed.

``NON_IID`` turns the heterogeneity up for the study (``python -m zk0.bench study``): the same
four clients, but each sees targets only in its own quarter of the table and its arm
approaches them at its own rate (as if each owner's teleoperation were faster or slower),
while the server's evaluation set spans the whole table at the clients' mean rate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from zk0.common import machine
from zk0.common.catalogue import Catalogue

JOINT_NAMES = (
    "shoulder_pan.pos",
    "shoulder_lift.pos",
    "elbow_flex.pos",
    "wrist_flex.pos",
    "wrist_roll.pos",
    "gripper.pos",
)
COLOURS = {
    "red": (220, 40, 40),
    "green": (40, 200, 60),
    "blue": (40, 70, 230),
    "yellow": (235, 215, 40),
    "orange": (245, 140, 30),
    "purple": (150, 60, 200),
}
HOME_POSE = np.array([0.0, -90.0, 90.0, 60.0, 0.0, 30.0], dtype=np.float32)
APPROACH_RATE = 0.2  # fraction of the remaining distance covered per frame


@dataclass(frozen=True)
class SyntheticSpec:
    """How one synthetic dataset looks; the registry names it by ``name``."""

    name: str
    repo_id: str
    robot_type: str
    task_template: str
    colours: tuple[str, ...]
    cameras: tuple[str, ...]
    height: int
    width: int
    episodes: int
    frames_per_episode: int
    fps: int
    target_region: tuple[float, float, float, float]  # x0, x1, y0, y1 as fractions of the image
    benchmark_only: bool = False  # generated on demand by benchmarks, not by `zk0 assets`
    approach_rate: float = APPROACH_RATE  # how fast the arm closes in on its target (the action dynamics)


_HAND_WRITTEN: dict[str, SyntheticSpec] = {
    spec.name: spec
    for spec in (
        SyntheticSpec(
            name="synth-so100-pickplace",
            repo_id="zk0/synth_so100_pickplace",
            robot_type="so100_follower",
            task_template="Pick up the {colour} cube and place it in the bin.",
            colours=("red", "green", "blue"),
            cameras=("front", "wrist"),
            height=48,
            width=64,
            episodes=8,
            frames_per_episode=24,
            fps=10,
            target_region=(0.1, 0.6, 0.3, 0.9),
        ),
        SyntheticSpec(
            name="synth-so100-stacking",
            repo_id="zk0/synth_so100_stacking",
            robot_type="so100_follower",
            task_template="Stack the {colour} block on the tower.",
            colours=("yellow", "red"),
            cameras=("laptop", "phone"),
            height=64,
            width=64,
            episodes=6,
            frames_per_episode=30,
            fps=15,
            target_region=(0.4, 0.9, 0.2, 0.7),
        ),
        SyntheticSpec(
            name="synth-so101-sorting",
            repo_id="zk0/synth_so101_sorting",
            robot_type="so101_follower",
            task_template="Sort the {colour} ball into its tray.",
            colours=("blue", "orange", "purple"),
            cameras=("top", "wrist"),
            height=48,
            width=80,
            episodes=10,
            frames_per_episode=20,
            fps=10,
            target_region=(0.2, 0.8, 0.1, 0.5),
        ),
        SyntheticSpec(
            name="synth-so101-reach",
            repo_id="zk0/synth_so101_reach",
            robot_type="so101_follower",
            task_template="Reach for the {colour} cup.",
            colours=("green", "purple", "yellow"),
            cameras=("front", "side"),
            height=56,
            width=72,
            episodes=7,
            frames_per_episode=26,
            fps=12,
            target_region=(0.05, 0.95, 0.5, 0.95),
        ),
        SyntheticSpec(
            name="synth-so100-eval",
            repo_id="zk0/synth_so100_eval",
            robot_type="so100_follower",
            task_template="Pick up the {colour} cube and place it in the bin.",
            colours=("red", "green", "blue", "yellow", "orange", "purple"),
            cameras=("front", "wrist"),
            height=48,
            width=64,
            episodes=6,
            frames_per_episode=24,
            fps=10,
            target_region=(0.05, 0.95, 0.1, 0.95),
        ),
        SyntheticSpec(  # an SO-100's real camera size, so decoding costs what it costs on a robot's data
            name="synth-so100-480p",
            repo_id="zk0/synth_so100_480p",
            robot_type="so100_follower",
            task_template="Pick up the {colour} cube and place it in the bin.",
            colours=("red", "green", "blue"),
            cameras=("front", "wrist"),
            height=480,
            width=640,
            episodes=6,
            frames_per_episode=60,
            fps=30,
            target_region=(0.1, 0.6, 0.3, 0.9),
            benchmark_only=True,
        ),
    )
}


# The study's strongly non-IID clients: (client dataset, its quarter of the table, its approach rate).
# The quarters are disjoint; the rates average to APPROACH_RATE, the server evaluation set's.
_NON_IID = (
    ("synth-so100-pickplace", (0.05, 0.5, 0.1, 0.5), 0.10),
    ("synth-so100-stacking", (0.5, 0.95, 0.1, 0.5), 0.15),
    ("synth-so101-sorting", (0.05, 0.5, 0.5, 0.95), 0.25),
    ("synth-so101-reach", (0.5, 0.95, 0.5, 0.95), 0.30),
)
NON_IID: dict[str, SyntheticSpec] = {
    f"{name}-noniid": replace(
        _HAND_WRITTEN[name],
        name=f"{name}-noniid",
        repo_id=f"{_HAND_WRITTEN[name].repo_id}_noniid",
        target_region=region,
        approach_rate=rate,
        benchmark_only=True,
    )
    for name, region, rate in _NON_IID
}
_HAND_WRITTEN.update(NON_IID)

OWNER_SEED = 2026  # owner N's conditions come from numpy's generator seeded with (OWNER_SEED, N)
_CLIENTS = tuple(_HAND_WRITTEN[name] for name, _, _ in _NON_IID)  # the four hand-written owners


def synth_owner(index: int) -> SyntheticSpec:
    """Owner ``index`` of a many-owner federation (``synth-owner-<index>``): its robot, task text and
    camera names those of one of the four hand-written owners, its colours (two or three of six),
    half-table region, image size, episode count and length, fps and approach rate drawn from a
    seeded distribution spanning theirs; the server's ``synth-so100-eval`` spans them all."""
    rng = np.random.default_rng([OWNER_SEED, index])
    like = _CLIENTS[int(rng.integers(len(_CLIENTS)))]
    size = _CLIENTS[int(rng.integers(len(_CLIENTS)))]
    x0, y0 = float(rng.uniform(0.05, 0.45)), float(rng.uniform(0.1, 0.5))
    colours = rng.choice(len(COLOURS), size=int(rng.integers(2, 4)), replace=False)
    return SyntheticSpec(
        name=f"synth-owner-{index}",
        repo_id=f"zk0/synth_owner_{index}",
        robot_type=like.robot_type,
        task_template=like.task_template,
        colours=tuple(list(COLOURS)[int(c)] for c in sorted(colours)),
        cameras=like.cameras,
        height=size.height,
        width=size.width,
        episodes=int(rng.integers(5, 9)),
        frames_per_episode=int(rng.integers(20, 31)),
        fps=int(rng.choice([10, 12, 15])),
        target_region=(x0, x0 + 0.5, y0, y0 + 0.45),
        approach_rate=float(rng.uniform(0.1, 0.3)),
    )


SPECS: Catalogue[SyntheticSpec] = Catalogue(
    _HAND_WRITTEN, {r"synth-owner-(?P<index>\d+)": lambda m: synth_owner(int(m["index"]))}, "synth-owner-<N>"
)


def target_pose(u: float, v: float, colour_index: int) -> np.ndarray:
    """The joint pose that reaches a target at image fraction (u, v); colour sets the wrist roll."""
    return np.array(
        [
            (u - 0.5) * 120.0,  # pan follows the horizontal position
            -60.0 + 50.0 * v,  # lift and elbow reach further for targets lower in the image
            70.0 - 60.0 * v,
            40.0 + 30.0 * (u - 0.5),
            -45.0 + 15.0 * colour_index,
            5.0,  # gripper closes on the target
        ],
        dtype=np.float32,
    )


def _draw_square(img: np.ndarray, cx: float, cy: float, half: int, rgb: tuple[int, int, int]) -> None:
    h, w, _ = img.shape
    x, y = int(cx * (w - 1)), int(cy * (h - 1))
    img[max(0, y - half) : min(h, y + half + 1), max(0, x - half) : min(w, x + half + 1)] = rgb


def _render(spec: SyntheticSpec, camera: int, u: float, v: float, rgb, state: np.ndarray, rng) -> np.ndarray:
    """One camera frame: table with noise, the target, and a grey marker where the gripper is."""
    img = np.full((spec.height, spec.width, 3), 110, dtype=np.uint8)
    img += rng.integers(0, 12, size=img.shape, dtype=np.uint8)
    gripper_u = float(np.clip(state[0] / 120.0 + 0.5, 0, 1))
    gripper_v = float(np.clip((state[1] + 60.0) / 50.0, 0, 1))
    size = max(2, spec.height // 12)
    if camera == 0:  # scene camera: target where it lies, gripper marker over it
        _draw_square(img, u, v, size, rgb)
        _draw_square(img, gripper_u, gripper_v, max(1, size // 2), (30, 30, 30))
    else:  # arm camera: the target as seen from the gripper, bigger as it gets close
        du, dv = 0.5 + (u - gripper_u), 0.5 + (v - gripper_v)
        closeness = 1.0 - min(1.0, abs(u - gripper_u) + abs(v - gripper_v))
        _draw_square(img, float(np.clip(du, 0, 1)), float(np.clip(dv, 0, 1)), size + int(3 * closeness), rgb)
    return img


def _features(spec: SyntheticSpec) -> dict:
    joint = {"dtype": "float32", "shape": (len(JOINT_NAMES),), "names": list(JOINT_NAMES)}
    features = {"observation.state": dict(joint), "action": dict(joint)}
    for cam in spec.cameras:
        features[f"observation.images.{cam}"] = {
            "dtype": "video",
            "shape": (spec.height, spec.width, 3),
            "names": ["height", "width", "channels"],
        }
    return features


def write_synthetic_dataset(spec: SyntheticSpec, root: Path, seed: int, episodes: int | None = None) -> Path:
    """Record ``spec`` into a LeRobotDataset (v3.0, mp4 video) at ``root``; deterministic in ``seed``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # only to write: reading SPECS stays light

    n_episodes = spec.episodes if episodes is None else episodes
    rng = np.random.default_rng([seed, sum(map(ord, spec.name))])
    dataset = LeRobotDataset.create(
        repo_id=spec.repo_id,
        fps=spec.fps,
        features=_features(spec),
        root=root,
        robot_type=spec.robot_type,
        use_videos=True,
    )
    _record(dataset, spec, rng, n_episodes)
    return root


def append_synthetic_episodes(spec: SyntheticSpec, root: Path, seed: int, episodes: int) -> Path:
    """Record ``episodes`` more of ``spec`` into the LeRobotDataset at ``root`` through lerobot's own
    ``LeRobotDataset.resume``, as an owner records more with ``lerobot-record --resume=true``
    (deterministic in ``seed`` and the count already there)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset.resume(spec.repo_id, root=root)
    rng = np.random.default_rng([seed, sum(map(ord, spec.name)), dataset.meta.total_episodes])
    _record(dataset, spec, rng, episodes)
    return root


def _record(dataset, spec: SyntheticSpec, rng: np.random.Generator, n_episodes: int) -> None:
    """``n_episodes`` of ``spec`` recorded into ``dataset`` (open for writing), then finalised."""
    x0, x1, y0, y1 = spec.target_region
    for _ in range(n_episodes):
        colour = spec.colours[int(rng.integers(len(spec.colours)))]
        colour_index = list(COLOURS).index(colour)
        u, v = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
        goal = target_pose(u, v, colour_index)
        state = HOME_POSE + rng.normal(0.0, 2.0, size=6).astype(np.float32)
        task = spec.task_template.format(colour=colour)
        for _ in range(spec.frames_per_episode):
            action = state + spec.approach_rate * (goal - state) + rng.normal(0.0, 0.3, size=6).astype(np.float32)
            frame = {"observation.state": state.copy(), "action": action.astype(np.float32), "task": task}
            for index, cam in enumerate(spec.cameras):
                frame[f"observation.images.{cam}"] = _render(spec, index, u, v, COLOURS[colour], state, rng)
            dataset.add_frame(frame)
            state = action
        with machine.ordinary_scheduling():  # libsvtav1 would leave this thread real-time
            dataset.save_episode(parallel_encoding=False)
    dataset.finalize()
