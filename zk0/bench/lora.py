"""LoRA against training in full, federated and centralised (``python -m zk0.bench learning --peft lora``).

lerobot adapts only pretrained weights, so every variant starts from one common pretrained
point: a short full federation's final checkpoint. From it the same rounds x steps x clients run
as federations through the real app (``flwr run``):

- ``full``: the trainable weights trained in full;
- ``lora b`` and ``lora ab``: LoRA on SmolVLA's default targets in both averaging modes (zk0.learning.adapters),
  every target adapted;
- ``lora b+proj`` (zk0's default): adapters on the action expert's q/v, with SmolVLA's five small
  state, action and time projections trained in full instead (``lora-full-modules``);

and, at equal samples (zk0.bench.study's centralised baseline: one policy on every client's
batches in turn), ``full``, ``lora b`` and ``lora b+proj`` trained centrally. The centralised
LoRA run splits LoRA's gap into what the adapters cannot learn (centralised LoRA against
centralised full) and what federating them costs (federated against centralised LoRA).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from zk0.bench.models import (
    EVAL_ALL,
    SERVER,
    centralised,
    evaluate_all,
    evaluation_sets,
    federate,
    sent_bytes,
    server_rows,
)
from zk0.config import LORA_FULL_MODULES, from_run_config
from zk0.data.registry import load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import snapshot


def variants(args: argparse.Namespace) -> dict[str, dict]:
    """Label -> the run-config keys each variant adds to the common start."""
    lora = {"peft": "lora", "lora-rank": args.lora_rank, "lr": args.lora_lr}
    return {
        "full": {},
        "lora b": {**lora, "lora-average": "b", "lora-full-modules": ""},
        "lora ab": {**lora, "lora-average": "ab", "lora-full-modules": ""},
        "lora b+proj": {**lora, "lora-average": "b", "lora-full-modules": LORA_FULL_MODULES},  # zk0's default
    }


CENTRALISED = ("full", "lora b", "lora b+proj")


def centralised_mse(args: argparse.Namespace, start: str, keys: dict) -> float:
    """Server action MSE of one variant trained centrally from ``start`` on the federation's samples."""
    run = from_run_config(
        {
            "model": start,
            "num-server-rounds": args.rounds,
            "local-steps": args.local_steps,
            "batch-size": args.batch_size,
            "lr": args.lr,
            "eval-batches": EVAL_ALL,
            "min-train-clients": args.clients,
            **keys,
        }
    )
    registry = load_registry(run.registry)
    cameras = registry.model_cameras()
    sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients[: args.clients])]
    weights, _ = centralised(sessions, run, snapshot(sessions[0].bundle), cameras)
    server = {SERVER: evaluation_sets(sessions, registry, run)[SERVER]}
    return evaluate_all({"trained": weights}, server, run)["trained"][SERVER]["action-mse"]


def lora_check(args: argparse.Namespace) -> int:
    """Every variant federated, and some centrally, from a common pretrained start; prints the table."""
    warmup = federate(args, args.warmup_rounds, "warmup")
    if warmup is None:
        return 1
    start = str(Path(warmup["run-dir"]) / "models" / f"checkpoint_round_{args.warmup_rounds}")
    results = {}
    for label, keys in variants(args).items():
        history = federate(args, args.rounds, label.replace(" ", "-").replace("+", "-"), model=start, **keys)
        if history is None:
            return 1
        rows = server_rows(history)
        results[label] = {
            "start-mse": rows[0]["action-mse"],
            "final-mse": rows[-1]["action-mse"],
            "final-policy-loss": rows[-1]["policy-loss"],
            "bytes-per-direction": sent_bytes(history),
            "wall-s": history["wall-s"],
            "rows": rows,
            "config": history["config"],
        }
        if label in CENTRALISED:
            results[label]["centralised-mse"] = centralised_mse(args, start, keys)
    print_table(args, results)
    if args.json:
        Path(args.json).write_text(json.dumps({"warmup-rounds": args.warmup_rounds, "results": results}, indent=2))
    return 0


def print_table(args: argparse.Namespace, results: dict[str, dict]) -> None:
    full = results["full"]
    print(
        f"start: round {args.warmup_rounds} of a full federation, server action MSE {full['start-mse']:.2f}; "
        f"then {args.rounds} rounds x {args.local_steps} steps x {args.clients} clients each, "
        f"and centrally on as many samples"
    )
    print(
        f"{'variant':>11} {'federated':>10} {'vs full':>8} {'centralised':>12} {'vs full':>8} {'fed/central':>12} "
        f"{'bytes/direction':>16}"
    )
    for label, r in results.items():
        central = r.get("centralised-mse")
        columns = (
            f"{central:>12.2f} {central / full['centralised-mse']:>8.3f} {r['final-mse'] / central:>12.3f}"
            if central
            else f"{'-':>12} {'-':>8} {'-':>12}"
        )
        print(
            f"{label:>11} {r['final-mse']:>10.2f} {r['final-mse'] / full['final-mse']:>8.3f} {columns} "
            f"{r['bytes-per-direction']:>16,}"
        )
