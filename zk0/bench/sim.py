"""Simulator benchmark: the scripted expert's success, rendering speed, CPU per episode, recording time.

Over ``--episodes`` seeded episodes in the server's conditions (every region and colour, a
distractor cube) it measures the expert's lift success and graded rates, the CPU seconds one
simulated and rendered episode costs (two cameras at ``--size``), and frames rendered per
second; then it times one full 10 s episode at 30 fps (the expert holds the cube to the end),
and ``--record N`` demonstrations written with lerobot's dataset writer.

    python -m zk0.bench sim [--episodes 100] [--size 128] [--record 20] [--json out.json]
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from zk0.bench.client import write_json
from zk0.errors import OneSentenceParser, positive
from zk0.sim.env import PickCubeEnv
from zk0.sim.expert import PickExpert
from zk0.sim.record import demonstrate, episode_seed, record_demonstrations
from zk0.sim.tasks import SIM_SPECS

CONDITIONS = "sim-so101-eval"


def expert_success(episodes: int, size: int) -> dict:
    """The expert over seeded episodes: success and graded rates, CPU s per episode, frames/s."""
    env = PickCubeEnv(SIM_SPECS[CONDITIONS].task, size, size)
    try:
        expert = PickExpert(env, SIM_SPECS[CONDITIONS].speed)
        outcomes, steps, cpu = [], 0, time.process_time()
        for index in range(episodes):
            frames, success = demonstrate(env, expert, episode_seed(1, "bench", index))
            outcomes.append({**env.outcome, "success": success})
            steps += len(frames)
        cpu = time.process_time() - cpu
    finally:
        env.close()
    rates = {f"{key}-rate": float(np.mean([o[key] for o in outcomes])) for key in outcomes[0]}
    return {**rates, "episodes": episodes, "mean-steps": steps / episodes, "cpu-s-per-episode": cpu / episodes,
            "frames-per-s": 2 * steps / cpu}


def full_episode(size: int) -> dict:
    """CPU and wall seconds of one whole 10 s, 30 fps episode (both cameras rendered every step)."""
    env = PickCubeEnv(SIM_SPECS[CONDITIONS].task, size, size)
    try:
        expert = PickExpert(env)
        env.reset(seed=0)
        expert.reset()
        cpu, wall = time.process_time(), time.perf_counter()
        for _ in range(env.task.max_steps):
            env.step(expert.act())
        return {"steps": env.task.max_steps, "cpu-s": time.process_time() - cpu, "wall-s": time.perf_counter() - wall}
    finally:
        env.close()


def recording(episodes: int, size: int) -> dict:
    """Seconds to record ``episodes`` demonstrations with lerobot's writer (video encoding included)."""
    spec = replace(SIM_SPECS["sim-so101-left"], height=size, width=size)
    with tempfile.TemporaryDirectory() as tmp:
        taken = record_demonstrations(spec, Path(tmp) / "demo", seed=0, episodes=episodes)
    return {**taken, "seconds-per-200": taken["seconds"] / episodes * 200}


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench sim", description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=positive(int), default=100, help="expert episodes (default 100)")
    parser.add_argument("--size", type=positive(int), default=128, help="camera height and width (default 128)")
    parser.add_argument("--record", type=positive(int), default=20, help="demonstrations to record (default 20)")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    figures = {
        "expert": expert_success(args.episodes, args.size),
        "full-episode": full_episode(args.size),
        "recording": recording(args.record, args.size),
        "size": args.size,
    }
    e, f, r = figures["expert"], figures["full-episode"], figures["recording"]
    print(f"expert over {e['episodes']} seeded episodes ({CONDITIONS}, distractor cube):")
    print(f"  success (lifted and held) {e['success-rate']:.0%}; reached {e['reached-rate']:.0%}, "
          f"grasped {e['grasped-rate']:.0%}, lifted {e['lifted-rate']:.0%}; {e['mean-steps']:.0f} steps per episode")
    print(f"  {e['cpu-s-per-episode']:.2f} CPU s per episode, {e['frames-per-s']:.0f} frames/s rendered "
          f"(two {args.size}x{args.size} cameras)")
    print(f"one full 10 s episode at 30 fps: {f['cpu-s']:.2f} CPU s ({f['wall-s']:.2f} s wall)")
    print(f"recording {r['episodes']} demonstrations: {r['seconds']:.1f} s ({r['attempts']} attempts); "
          f"200 would take {r['seconds-per-200'] / 60:.1f} min")
    write_json(args.json, figures)
    return 0
