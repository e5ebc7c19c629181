"""Sim learning: does a centrally trained policy pick the cube up? Success rate along training.

One policy is trained on every simulated owner's demonstrations pooled (the study's centralised
baseline, ``zk0.learning.training.PooledTrainer``: each batch through its own client's processors) and
rolled out in the simulator every ``--every`` steps on the same seeded episodes in the server's
conditions, as the federation's closed-loop evaluation does: success, graded rates (reached,
grasped, lifted) and CPU time, so a learning curve in success rate rather than action MSE. The
first episode of each rollout is saved as a video next to the JSON.

    python -m zk0.bench sim-learning [--policy smolvla] [--model tiny-128] [--demos 100] [--steps 8000]
        [--every 2000] [--sim-episodes 20] [--registry configs/sim-registry.toml] [--json out.json]

``--registry configs/sim-cube-registry.toml`` trains and rolls out with the target cube's xy in the
state (privileged; docs/learning.md): what the policy does once it need not locate the cube.
"""

from __future__ import annotations

import time
from pathlib import Path

from zk0.bench.client import write_json
from zk0.bench.models import generate
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import OFFLINE_MODELS, POLICIES, RunConfig
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import build_policy, set_trainable, snapshot
from zk0.learning.policy_types import NAMES
from zk0.learning.training import PooledTrainer

REGISTRY = "configs/sim-registry.toml"
REGISTRIES = (REGISTRY, "configs/sim-cube-registry.toml")  # from the frames; told where the cube is


def rollout_rows(run: RunConfig, steps: int, every: int, episodes: int, videos: Path | None) -> list[dict]:
    """Train centrally for ``steps`` and roll out after every ``every``: one row per rollout."""
    from zk0.learning.closed_loop import ClosedLoop  # MuJoCo: loaded only to roll out

    registry = load_registry(run.registry)
    server = registry.get(run.server_eval_dataset)
    cameras = registry.model_cameras()
    sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients)]
    bundle = build_policy(run, sessions[0].split.meta, sessions[0].split.entry, cameras)
    trainer = PooledTrainer.over(bundle, [s.trainer for s in sessions], run)
    judge = build_policy(run, open_metadata(server), server, cameras)  # the server's processors, as it rolls out
    height, width, _ = sessions[0].split.meta.features["observation.images.front"]["shape"]
    loop = ClosedLoop(server.name, episodes, run.seed, height, width)
    rows, done, cpu = [], 0, time.process_time()
    try:
        while done < steps:
            chunk = min(every, steps - done)
            trained = trainer.fit(chunk, mu=0.0, global_step=done)
            done += chunk
            set_trainable(judge, snapshot(bundle))
            video = videos / f"steps_{done}.mp4" if videos else None
            rates = loop(judge, video)
            rows.append({"steps": done, "train-loss": trained["train-loss"], "step-time": trained["step-time"],
                         **rates, "cpu-s": time.process_time() - cpu})
            print(f"{done:>6} steps  loss {trained['train-loss']:.3f}  success {rates['success-rate']:.0%}  "
                  f"reached {rates['reached-rate']:.0%}  grasped {rates['grasped-rate']:.0%}  "
                  f"lifted {rates['lifted-rate']:.0%}  ({rates['sim-eval-s']:.0f} s rollout)", flush=True)
    finally:
        loop.close()
    return rows


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench sim-learning", description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="smolvla", choices=POLICIES, help="the lerobot policy type trained")
    parser.add_argument("--model", default="tiny-128", choices=OFFLINE_MODELS)
    parser.add_argument("--demos", type=positive(int), default=100, help="demonstrations per simulated client")
    parser.add_argument("--steps", type=positive(int), default=8000, help="centralised training steps")
    parser.add_argument("--every", type=positive(int), default=2000, help="roll out after every this many steps")
    parser.add_argument("--sim-episodes", type=positive(int), default=20, help="seeded episodes per rollout")
    parser.add_argument("--lr", type=positive(float), default=1e-3)
    parser.add_argument("--batch-size", type=positive(int), default=8)
    parser.add_argument("--registry", default=REGISTRY, choices=REGISTRIES, help="the simulated owners and server set")
    parser.add_argument("--json", help="also write the figures to this JSON file (videos next to it)")
    return parser


def main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    registry = load_registry(args.registry)
    generate(registry, args.demos)
    server = registry.server
    run = RunConfig(registry=args.registry, server_eval_dataset=server.name, model=args.model, policy=args.policy,
                    batch_size=args.batch_size, lr=args.lr, local_steps=args.steps)
    videos = Path(args.json).with_suffix("") if args.json else None
    if videos:
        videos.mkdir(parents=True, exist_ok=True)
    print(f"centralised {args.model} {NAMES[args.policy]} on {len(registry.clients)} simulated owners' demonstrations "
          f"({args.demos} each), rolled out on {args.sim_episodes} seeded episodes of {server.name}:")
    rows = rollout_rows(run, args.steps, args.every, args.sim_episodes, videos)
    write_json(args.json, {"policy": args.policy, "model": args.model, "registry": args.registry, "demos-per-client": args.demos,
                           "batch-size": args.batch_size, "lr": args.lr, "sim-episodes": args.sim_episodes, "rows": rows})
    return 0
