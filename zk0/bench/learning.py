"""Learning check: does the federation learn something a mean-action guess cannot?

Runs the real app (`flwr run`, 4 simulated clients on the synthetic SO-100/SO-101
datasets, tiny SmolVLA on the CPU) for several rounds, then prints the server's action
MSE on its own evaluation dataset after every round next to the MSE of always predicting
the clients' mean action.

    python -m zk0.bench learning [--rounds 20] [--local-steps 25] [--json out.json]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from zk0.errors import OneSentenceParser
from zk0.registry import load_registry
from zk0.simulation import run_federation


def actions(entry, episodes: list[int] | None = None) -> np.ndarray:
    """Every recorded action of a dataset (or of some of its episodes)."""
    dataset = LeRobotDataset(entry.repo_id, root=entry.local_root(), episodes=episodes)
    return np.stack(dataset.hf_dataset["action"]).astype(np.float64)


def mean_action_baseline(eval_dataset: str, eval_episodes: int) -> float:
    """MSE on the server's evaluation actions of predicting the mean of the clients' training actions."""
    registry = load_registry()
    train = []
    for entry in registry.clients:
        total = LeRobotDataset(entry.repo_id, root=entry.local_root()).num_episodes
        train.append(actions(entry, list(range(total - eval_episodes))))
    mean = np.concatenate(train).mean(axis=0)
    target = actions(registry.get(eval_dataset))
    return float(((target - mean) ** 2).mean())


def main(argv: list[str] | None = None) -> int:
    parser = OneSentenceParser(prog="python -m zk0.bench learning", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--local-steps", type=int, default=25)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--wire-dtype", default="bfloat16", choices=["bfloat16", "float32"])
    parser.add_argument("--output-dir", default="outputs/bench-learning")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)

    run_config = (
        f"num-server-rounds={args.rounds} local-steps={args.local_steps} batch-size={args.batch_size} "
        f"lr={args.lr} eval-batches=1000 checkpoint-interval={args.rounds} min-train-clients={args.clients} "
        f"wire-dtype='{args.wire_dtype}'"
    )
    started = time.perf_counter()
    history = run_federation(run_config, args.clients, Path(args.output_dir).resolve(), "bench.learning")
    wall = time.perf_counter() - started
    if history is None:
        return 1
    baseline = mean_action_baseline("synth-so100-eval", eval_episodes=2)

    print(f"{'round':>5} {'server action MSE':>18} {'mean-action MSE':>16} {'ratio':>6} {'server policy loss':>19}")
    rows = []
    for record in history["rounds"]:
        server = record.get("server-evaluate")
        if not server:
            continue
        ratio = server["action-mse"] / baseline
        rows.append({"round": record["round"], **server, "baseline-mse": baseline, "ratio": ratio})
        print(
            f"{record['round']:>5} {server['action-mse']:>18.2f} {baseline:>16.2f} {ratio:>6.3f} {server['policy-loss']:>19.4f}"
        )
    print(
        f"wall time: {wall:.1f} s for {args.rounds} rounds x {args.local_steps} steps x {args.clients} clients; run: {history['run-dir']}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "wall-s": wall, "config": run_config}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
