"""Simulator benchmark: the scripted expert's success, rendering speed, CPU per episode, recording
time, and what closed-loop evaluation of a policy costs.

Over ``--episodes`` seeded episodes in the server's conditions (every region and colour, a
distractor cube) it measures the expert's success and graded rates (with their 95% interval) in
each task of ``--kinds`` (default the pick-up; place, stack, sort: zk0.sim.tasks.KINDS),
the CPU seconds one simulated and rendered episode costs (two cameras at ``--size``), and frames
rendered per second; then it times one full 10 s episode at 30 fps (the expert holds the cube to
the end), and ``--record N`` demonstrations written with lerobot's dataset writer. Last, an
untrained ``tiny-128`` SmolVLA (it fails, so every episode runs its 300 steps) is rolled out on
``--policy-episodes`` episodes by zk0's closed loop, and on ``--reference-episodes`` of them by
lerobot's own ``eval_policy`` as zk0 ran it before (one env, every frame rendered), in the same run:
seconds per episode of each and their ratio. ``--expert-only`` stops after the expert's success.

    python -m zk0.bench sim [--episodes 100] [--kinds pick place stack sort] [--expert-only] [--size 128]
        [--record 20] [--policy-episodes 100] [--reference-episodes 5] [--json out.json]
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser, positive
from zk0.learning.rates import rate_text
from zk0.sim.env import PickCubeEnv
from zk0.sim.expert import PickExpert
from zk0.sim.record import demonstrate, episode_seed, record_demonstrations
from zk0.sim.tasks import KINDS, SIM_SPECS

CONDITIONS = "sim-so101-eval"
SIM_REGISTRY = "configs/sim-registry.toml"


def expert_success(episodes: int, size: int, kind: str = "pick") -> dict:
    """The expert over seeded episodes of one task: success and graded rates, CPU s per episode, frames/s."""
    env = PickCubeEnv(replace(SIM_SPECS[CONDITIONS].task, kind=kind), size, size)
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


def closed_loop_cost(episodes: int, reference: int) -> dict:
    """Seconds per episode of a failing tiny-128 policy: zk0's closed loop against lerobot's
    ``eval_policy`` on one env, on the first ``reference`` of the same seeded episodes."""
    from lerobot.envs.factory import make_env
    from lerobot.scripts.lerobot_eval import eval_policy

    from zk0.config import RunConfig
    from zk0.data.assets import ensure_dataset
    from zk0.data.loaders import open_metadata
    from zk0.data.registry import load_registry
    from zk0.learning.closed_loop import ClosedLoop
    from zk0.learning.policy import build_policy

    registry = load_registry(SIM_REGISTRY)
    entry = registry.get(CONDITIONS)
    ensure_dataset(entry.name)
    run = RunConfig(registry=SIM_REGISTRY, server_eval_dataset=CONDITIONS, model="tiny-128")
    bundle = build_policy(run, open_metadata(entry), entry, registry.model_cameras())
    loop = ClosedLoop(CONDITIONS, episodes, run.seed, 128, 128)
    env = make_env(loop.config, n_envs=1)[loop.config.type][0]
    try:
        wall = time.perf_counter()
        rates = loop(bundle)
        fast = time.perf_counter() - wall
        wall = time.perf_counter()
        eval_policy(env, bundle.policy, loop.env_preprocessor, loop.env_postprocessor, bundle.preprocessor,
                    bundle.postprocessor, n_episodes=reference, start_seed=run.seed)  # fmt: skip
        slow = time.perf_counter() - wall
    finally:
        env.close()
        loop.close()
    return {"episodes": episodes, "batch": loop.batch, "seconds": fast, "seconds-per-episode": fast / episodes,
            "reference-episodes": reference, "reference-seconds-per-episode": slow / reference,
            "speed-up": (slow / reference) / (fast / episodes), "episode-length": rates["episode-length"]}  # fmt: skip


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench sim", description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=positive(int), default=100, help="expert episodes (default 100)")
    parser.add_argument(
        "--kinds", nargs="+", choices=KINDS, default=["pick"], help="the tasks whose expert is measured (default pick)"
    )
    parser.add_argument("--expert-only", action="store_true", help="stop after the expert's success")
    parser.add_argument("--size", type=positive(int), default=128, help="camera height and width (default 128)")
    parser.add_argument("--record", type=positive(int), default=20, help="demonstrations to record (default 20)")
    parser.add_argument("--policy-episodes", type=positive(int), default=100, help="closed-loop episodes (default 100)")
    parser.add_argument(
        "--reference-episodes", type=positive(int), default=5, help="of them through lerobot's eval_policy (default 5)"
    )
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    figures = {"tasks": {}, "size": args.size}
    for kind in dict.fromkeys(args.kinds):
        e = figures["tasks"][kind] = expert_success(args.episodes, args.size, kind)
        grades = ", ".join(f"{key.removesuffix('-rate')} {e[key]:.0%}" for key in e if key.endswith("-rate") and key != "success-rate")
        print(f"expert, {kind}, over {e['episodes']} seeded episodes ({CONDITIONS}, two cubes):")
        print(f"  success {rate_text(e['success-rate'], e['episodes'])}; {grades}; {e['mean-steps']:.0f} steps per episode")
        print(f"  {e['cpu-s-per-episode']:.2f} CPU s per episode, {e['frames-per-s']:.0f} frames/s rendered "
              f"(two {args.size}x{args.size} cameras)")
    if "pick" in figures["tasks"]:
        figures["expert"] = figures["tasks"]["pick"]  # where earlier figures keep the pick-up's
    if args.expert_only:
        write_json(args.json, figures)
        return 0
    figures |= {
        "full-episode": full_episode(args.size),
        "recording": recording(args.record, args.size),
        "closed-loop": closed_loop_cost(args.policy_episodes, args.reference_episodes),
    }
    f, r, c = figures["full-episode"], figures["recording"], figures["closed-loop"]
    print(f"one full 10 s episode at 30 fps: {f['cpu-s']:.2f} CPU s ({f['wall-s']:.2f} s wall)")
    print(f"recording {r['episodes']} demonstrations: {r['seconds']:.1f} s ({r['attempts']} attempts); "
          f"200 would take {r['seconds-per-200'] / 60:.1f} min")
    print(f"closed loop, untrained tiny-128 ({c['episode-length']:.0f} steps an episode): {c['episodes']} episodes in "
          f"{c['seconds']:.0f} s ({c['seconds-per-episode']:.2f} s each, {c['batch']} at a time); lerobot's eval_policy on "
          f"one env: {c['reference-seconds-per-episode']:.2f} s each ({c['reference-episodes']} episodes): "
          f"{c['speed-up']:.1f}x faster")
    write_json(args.json, figures)
    return 0
