"""Demonstrations: the scripted expert's episodes, recorded with lerobot's own dataset writer.

Each dataset is a LeRobotDataset (v3.0, video cameras, ``stats.json``) shaped exactly like a
real SO-101 recording: ``observation.state`` and ``action`` as the six ``*.pos`` values,
``observation.images.front`` and ``.wrist``, the task sentence per episode. Only episodes the
expert completed are kept, as an owner discards a failed take; everything is a function of
the spec and the seed. A ``-cube`` set-up's state also carries the target cube's xy (privileged,
for the study only).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from zk0.common import machine
from zk0.sim.env import JOINTS, PickCubeEnv, privileged_names
from zk0.sim.expert import PickExpert
from zk0.sim.tasks import CAMERAS, DemoSpec, SimTask

JOINT_NAMES = tuple(f"{joint}.pos" for joint in JOINTS)  # as lerobot's SO-101 follower names its motors


def features(task: SimTask, height: int, width: int) -> dict:
    """The dataset features of a real SO-101 recording with two cameras (the state with the cubes'
    and places' xy after the joints in a ``cube_in_state`` task)."""
    joint = {"dtype": "float32", "shape": (len(JOINT_NAMES),), "names": list(JOINT_NAMES)}
    state_names = [*JOINT_NAMES, *privileged_names(task)]
    state = {"dtype": "float32", "shape": (len(state_names),), "names": state_names}
    image = {"dtype": "video", "shape": (height, width, 3), "names": ["height", "width", "channels"]}
    return {"observation.state": state, "action": joint, **{f"observation.images.{c}": image for c in CAMERAS}}


def episode_seed(seed: int, name: str, index: int) -> int:
    """The env seed of attempt ``index`` of dataset ``name``: distinct across datasets and attempts."""
    return int(np.random.SeedSequence([seed, sum(map(ord, name)), index]).generate_state(1)[0])


def demonstrate(env: PickCubeEnv, expert: PickExpert, seed: int) -> tuple[list[dict], bool]:
    """One expert episode: its frames (observation, action, task) and whether it succeeded."""
    observation, _ = env.reset(seed=seed)
    expert.reset()
    frames, success = [], False
    for _ in range(env.task.max_steps):
        action = expert.act().astype(np.float32)
        frame = {"observation.state": observation["agent_pos"], "action": action, "task": env.task_description}
        frames.append(frame | {f"observation.images.{c}": observation["pixels"][c] for c in CAMERAS})
        observation, _, success, _, _ = env.step(action)
        if success:
            break
    return frames, bool(success)


def record_demonstrations(spec: DemoSpec, root: Path, seed: int, episodes: int | None = None) -> dict:
    """Record ``episodes`` (default ``spec.episodes``) successful expert episodes into a
    LeRobotDataset at ``root`` (a multi-task set-up's kinds in turn); returns what it took
    (attempts, successes, seconds)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    wanted = spec.episodes if episodes is None else episodes
    started = time.perf_counter()
    envs = [PickCubeEnv(task, spec.height, spec.width) for task in spec.tasks]
    try:
        experts = [PickExpert(env, spec.speed) for env in envs]
        dataset = LeRobotDataset.create(
            repo_id=spec.repo_id,
            fps=spec.task.fps,
            features=features(spec.task, spec.height, spec.width),
            root=root,
            robot_type="so101_follower",
            use_videos=True,
        )
        attempts = kept = 0
        while kept < wanted:
            if attempts >= 2 * wanted + 10:
                raise RuntimeError(f"The expert succeeded in {kept} of {attempts} episodes of {spec.name!r}.")
            turn = kept % len(envs)  # a multi-task set-up's episodes take its kinds in turn
            frames, success = demonstrate(envs[turn], experts[turn], episode_seed(seed, spec.name, attempts))
            attempts += 1
            if not success:
                continue
            for frame in frames:
                dataset.add_frame(frame)
            with machine.ordinary_scheduling():  # libsvtav1 would leave this thread real-time
                dataset.save_episode(parallel_encoding=False)
            kept += 1
        dataset.finalize()
    finally:
        for env in envs:
            env.close()
    return {"attempts": attempts, "episodes": kept, "seconds": time.perf_counter() - started}
