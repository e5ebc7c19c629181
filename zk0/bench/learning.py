"""Learning check: does the federation learn something a mean-action guess cannot?

Runs the real app (`flwr run`, 4 simulated clients on the synthetic SO-100/SO-101
datasets, tiny SmolVLA on the CPU) for several rounds, then prints the server's action
MSE on its own evaluation dataset after every round next to the MSE of always predicting
the clients' mean action.

With ``--peft lora`` it compares LoRA with training in full instead, federated and centralised,
from a common pretrained start (zk0.bench.lora).

    python -m zk0.bench learning [--rounds 20] [--local-steps 25] [--json out.json]
    python -m zk0.bench learning --peft lora [--warmup-rounds 10] [--rounds 10] [--lora-lr 2e-2]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from zk0.bench.lora import lora_check
from zk0.bench.models import federate, server_rows
from zk0.common.errors import OneSentenceParser, positive
from zk0.data.registry import load_registry


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


def mean_action_check(args) -> int:
    """The federation against always predicting the clients' mean action."""
    history = federate(args, args.rounds, "federation")
    if history is None:
        return 1
    baseline = mean_action_baseline("synth-so100-eval", eval_episodes=2)
    print(f"{'round':>5} {'server action MSE':>18} {'mean-action MSE':>16} {'ratio':>6} {'server policy loss':>19}")
    rows = []
    for row in server_rows(history):
        ratio = row["action-mse"] / baseline
        rows.append({**row, "baseline-mse": baseline, "ratio": ratio})
        print(
            f"{row['round']:>5} {row['action-mse']:>18.2f} {baseline:>16.2f} {ratio:>6.3f} {row['policy-loss']:>19.4f}"
        )
    print(
        f"wall time: {history['wall-s']:.1f} s for {args.rounds} rounds x {args.local_steps} steps x {args.clients} clients; run: {history['run-dir']}"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"rows": rows, "wall-s": history["wall-s"], "config": history["config"]}, indent=2)
        )
    return 0


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench learning", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--local-steps", type=int, default=25)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--wire-dtype", default="bfloat16", choices=["bfloat16", "float32"])
    parser.add_argument("--peft", choices=["none", "lora"], default="none", help="lora: LoRA against training in full")
    parser.add_argument(
        "--warmup-rounds", type=positive(int), default=10, help="--peft lora: rounds of the common start"
    )
    parser.add_argument("--lora-rank", type=positive(int), default=16)
    parser.add_argument(
        "--lora-lr", type=positive(float), default=2e-2, help="--peft lora: the adapters' learning rate"
    )
    parser.add_argument("--output-dir", default="outputs/bench-learning")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.peft == "lora":
        return lora_check(args)
    return mean_action_check(args)


if __name__ == "__main__":
    sys.exit(main())
