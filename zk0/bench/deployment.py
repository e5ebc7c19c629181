"""Deployment benchmark: the same federation on a loopback Deployment Engine and in simulation.

The Deployment Engine run is what robot owners run: a TLS SuperLink with SuperNode
authentication and one ``zk0 supernode`` per client, each in its own folder (``zk0.deployment.loopback``).
The simulation run is ``flwr run`` on a local simulation SuperLink (Ray). They run one after
the other, ``--repeats`` times, interleaved. Printed: the wall time of every round of both,
their ratio over the steady rounds (round 1 also builds every client), and for the deployment
where a client's message time goes, from the timings every reply carries: the ClientApp
process's start and imports, the client build, restoring training state, the local steps or the
evaluation, and handing the message to the warm worker and back. The fixed cost per client and
round is everything that is not local steps or evaluation, given for each steady round and for
the middle ones apart (the last round also writes the checkpoint and sends an evaluate message).
``--supernode-defaults`` also runs the deployment with ``zk0 supernode``'s default CPU share (no
``--cpus``: the SuperNodes divide the machine, zk0.common.machine), next to the ``--cpus-per-node`` one.

    python -m zk0.bench deployment [--model full-size] [--rounds 3] [--local-steps 30] [--clients 2]
        [--batch-size 8] [--cpus-per-node N] [--supernode-defaults] [--peft lora] [--no-simulation]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

from zk0.bench.client import starting_checkpoint, write_json
from zk0.common.errors import OneSentenceParser
from zk0.data.registry import load_registry
from zk0.deployment.loopback import loopback_federation
from zk0.deployment.simulation import run_federation


def run_config(args: argparse.Namespace) -> str:
    """The run's keys; with ``--peft lora`` from the LoRA starting checkpoint of ``--model``."""
    model = starting_checkpoint(args.model) if args.peft == "lora" else args.model
    return (
        f"num-server-rounds={args.rounds} local-steps={args.local_steps} batch-size={args.batch_size} "
        f"eval-batches={args.eval_batches} model='{model}' min-train-clients={args.clients} "
        f"checkpoint-interval={args.rounds} num-workers={args.num_workers} peft='{args.peft}'"
    )


def deployment_history(args: argparse.Namespace, root: Path, cpus: int | None) -> dict | None:
    """One run on a loopback Deployment Engine, each SuperNode with ``--cpus cpus`` (None: its default);
    its metric history, or None (with the log) on failure."""
    datasets = [entry.name for entry in load_registry().clients[: args.clients]]
    supernodes = {f"robot-{i}": name for i, name in enumerate(datasets)}
    with loopback_federation(root, supernodes, cpus=cpus) as fed:
        return fed.run_history(run_config(args), root / "server-outputs", "bench.deployment")


def round_walls(history: dict) -> list[float]:
    walls = {r["round"]: r["wall-s"] for r in history["rounds"]}
    return [walls[r] - walls[r - 1] for r in range(1, max(walls) + 1)]


def message_breakdown(history: dict, steps: int) -> dict[str, dict[str, float]]:
    """Mean seconds per client message of the steady rounds, by where they went."""
    parts: dict[str, dict[str, list[float]]] = {"train": {}, "evaluate": {}}
    for record in history["rounds"][2:]:  # round 0 is the server's, round 1 builds
        for client in record.get("clients", {}).values():
            for phase in ("train", "evaluate"):
                if "handler-s" not in client.get(phase, {}):
                    continue  # an evaluation that came inside a train message has no message of its own
                m = client[phase]
                steps_s = m["step-time"] * steps if phase == "train" else 0.0
                eval_s = m["evaluate-s"] if phase == "train" else m["eval-s"]
                work = steps_s + eval_s
                worker_rest = m["worker-s"] - m["build-s"] - m["restore-s"] - work if m["worker-s"] else 0.0
                own = m["handler-s"] - (m["worker-s"] or m["handler-s"])
                for name, value in {
                    "ClientApp start, message in": m["startup-s"],
                    "client build": m["build-s"],
                    "state restore": m["restore-s"],
                    "local steps": steps_s,
                    "evaluation": eval_s,
                    "to the worker and back": own,
                    "weights in/out, metrics": worker_rest,
                }.items():
                    parts[phase].setdefault(name, []).append(value)
    return {phase: {k: statistics.mean(v) for k, v in p.items()} for phase, p in parts.items() if p}


def fixed_costs(history: dict, steps: int) -> list[float]:
    """Seconds of each steady round (round 2 on) beyond the slowest client's local steps and the
    evaluations that ran in it. The last round also sends an evaluate message of its own and writes
    the run's checkpoint, so it costs more than a middle round."""
    walls = round_walls(history)
    costs = []
    for record in history["rounds"][2:]:
        clients = [c for c in record["clients"].values() if "train" in c]
        if not clients:
            raise RuntimeError(f"No client trained in round {record['round']}; see the clients' logs.")
        # A client's evaluation of the round's model mostly rides on the next round's train message
        # (in its evaluate-s); only an evaluate message of its own (the last round's) ran in this round.
        work = max(c["train"]["step-time"] * steps + c["train"]["evaluate-s"] for c in clients)
        work += max((c["evaluate"]["eval-s"] for c in clients if "handler-s" in c.get("evaluate", {})), default=0.0)
        work += record.get("server-evaluate", {}).get("eval-s", 0.0)
        costs.append(walls[record["round"] - 1] - work)
    return costs


def fixed_cost_figures(costs: list[list[float]]) -> dict:
    """Each run's fixed cost by steady round, their mean, and the mean of the middle rounds (all
    but the last; none with two rounds): what every round but the final one pays."""
    middle = [c for run in costs for c in run[:-1]]
    return {
        "fixed-cost-by-round-s": costs,
        "fixed-cost-per-round-s": statistics.mean(c for run in costs for c in run),
        "fixed-cost-middle-round-s": statistics.mean(middle) if middle else None,
    }


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench deployment", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="tiny", help="tiny, full-size, or a SmolVLA checkpoint")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--local-steps", type=int, default=30)
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--eval-batches", type=int, default=1)
    parser.add_argument("--num-workers", type=int, default=0, help="DataLoader workers per client")
    parser.add_argument(
        "--cpus-per-node", type=int, help="zk0 supernode --cpus (default: the machine's CPUs / clients)"
    )
    parser.add_argument(
        "--peft", choices=["none", "lora"], default="none", help="lora: LoRA adapters travel (run-config peft)"
    )
    parser.add_argument(
        "--supernode-defaults", action="store_true", help="also run the SuperNodes without --cpus (their default share)"
    )
    parser.add_argument("--repeats", type=int, default=1, help="simulation/deployment pairs, interleaved")
    parser.add_argument("--no-simulation", action="store_true", help="deployment only (no Ray on this machine)")
    parser.add_argument("--keep", action="store_true", help="keep the runs' folders (printed) for their logs")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.rounds < 2:
        parser.error("--rounds must be at least 2: round 1 builds every client, the steady state starts at 2.")
    if args.cpus_per_node is None:
        args.cpus_per_node = max(1, len(os.sched_getaffinity(0)) // args.clients)

    runs: dict[str, list[dict]] = {"simulation": [], "deployment": [], "deployment-defaults": []}
    with tempfile.TemporaryDirectory(prefix="zk0-bench-deployment-", delete=not args.keep) as tmp:
        for repeat in range(args.repeats):
            if not args.no_simulation:
                out = Path(tmp) / f"simulation-{repeat}"
                history = run_federation(run_config(args), args.clients, out, "bench.deployment")
                if history is None:
                    return 1
                runs["simulation"].append(history)
            history = deployment_history(args, Path(tmp) / f"deployment-{repeat}", args.cpus_per_node)
            if history is None:
                return 1
            runs["deployment"].append(history)
            if args.supernode_defaults:
                history = deployment_history(args, Path(tmp) / f"defaults-{repeat}", None)
                if history is None:
                    return 1
                runs["deployment-defaults"].append(history)
        if args.keep:
            print(f"runs kept in {tmp}")

    figures: dict = {"settings": vars(args)}
    for mode, histories in runs.items():
        if not histories:
            continue
        walls = [round_walls(h) for h in histories]
        figures[mode] = {
            "round-wall-s": walls,
            "steady-round-s": statistics.mean(w for ws in walls for w in ws[1:]),
            **fixed_cost_figures([fixed_costs(h, args.local_steps) for h in histories]),
            "step-s": statistics.mean(
                c["train"]["step-time"] for h in histories for r in h["rounds"][2:] for c in r["clients"].values()
            ),
            "local-steps-s": statistics.mean(
                c["train"]["step-time"] * args.local_steps
                for h in histories
                for r in h["rounds"][2:]
                for c in r["clients"].values()
            ),
        }
    figures["deployment"]["messages"] = message_breakdown(runs["deployment"][-1], args.local_steps)

    print(
        f"model {args.model} (peft {args.peft}), {args.clients} clients, {args.rounds} rounds x {args.local_steps} steps, "
        f"batch {args.batch_size}, {args.cpus_per_node} CPU(s) per SuperNode"
    )
    for mode in ("simulation", "deployment", "deployment-defaults"):
        if mode in figures:
            f = figures[mode]
            walls = " ".join(f"{w:.2f}" for w in f["round-wall-s"][-1])
            print(
                f"{mode:>19}: rounds {walls} s; steady {f['steady-round-s']:.2f} s/round, of which local steps "
                f"{f['local-steps-s']:.2f} s ({f['step-s']:.3f} s/step) and fixed cost {f['fixed-cost-per-round-s']:.2f} s"
            )
    if "simulation" in figures:
        for mode in ("deployment", "deployment-defaults"):
            if mode in figures:
                figures[f"ratio-{mode}"] = figures[mode]["steady-round-s"] / figures["simulation"]["steady-round-s"]
                print(f"{mode} / simulation, steady rounds: {figures[f'ratio-{mode}']:.2f}x")
    d = figures["deployment"]
    print(f"deployment overhead: {100 * d['fixed-cost-per-round-s'] / d['steady-round-s']:.1f}% of a steady round")
    print("fixed cost by steady round: " + " ".join(f"{c:.2f}" for c in d["fixed-cost-by-round-s"][-1]) + " s")
    if d["fixed-cost-middle-round-s"] is not None:
        middle = d["fixed-cost-middle-round-s"]
        print(f"fixed cost of a middle round (no checkpoint, no evaluate message of its own): {middle:.2f} s")
    for phase, parts in d["messages"].items():
        print(f"  {phase} message (mean per client, steady rounds):")
        for name, seconds in parts.items():
            print(f"    {name:<26} {seconds:8.3f} s")
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
