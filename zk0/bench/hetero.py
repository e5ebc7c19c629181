"""Hetero benchmark: owners with different hardware, fixed steps against a time budget.

One loopback Deployment Engine federation (``zk0.deployment.loopback``: a TLS SuperLink and one
``zk0 supernode`` per owner) in which the last ``--slow`` owners' SuperNodes are each held to
``--share`` of the CPU for the whole benchmark (``zk0.bench.throttle``: SIGSTOP/SIGCONT
duty-cycling, as cpulimit does). Three runs on it, one after another: every client taking
``--local-steps`` a round (today's default: each round waits for the slow owners), and
``local-time-s = --budget`` (with ``round-deadline-s = --deadline``) averaged with FedNova's
normalisation and with plain sample weighting. For each: the wall time of every round after the
first (which builds the clients) and before the last (which evaluates every client in a message
of its own, and checkpoints), its ratio to the budget, the slow owners' step time against the
others' (how slow the throttle made them, measured) and their share of the steps, the clients
each round named as stragglers or late, and the server's action MSE per round, compared at equal
wall time (counted from the end of round 1, which builds every client): each budget run's final
model against the fixed-steps model of the last round that had ended by then.

``--setting sim-cube`` (simulated SO-101 owners told where the cube is, as the study's) also keeps
every round's checkpoint and, once the runs are over (unthrottled), rolls the compared models out
on the same ``--sim-episodes`` seeded episodes in the server's conditions: each budget run's final
model against fixed steps' at equal wall time, and against fixed steps' final model (equal rounds),
each with its 95% interval and McNemar's test. Every round's checkpoint is in every run's round
time, so the budget runs, which fit more rounds in a wall time, pay for more of them.

    python -m zk0.bench hetero [--setting mild|noniid|sim-cube] [--clients 4] [--slow 1] [--rounds 6] [--local-steps 100]
        [--budget 10] [--deadline 30] [--share 0.25] [--batch-size 8] [--lr 2e-3] [--model tiny] [--demos 30]
        [--sim-episodes 100] [--json FILE]
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

from zk0.artifacts.logs import native_output_to
from zk0.artifacts.resume import checkpoint_trainable
from zk0.artifacts.run_folder import checkpoints
from zk0.bench.client import write_json
from zk0.bench.models import SERVER, closed_loop_all, generate
from zk0.bench.throttle import Throttle
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.data.loaders import open_evaluation, open_metadata
from zk0.data.registry import PROJECT_ROOT, Registry, load_registry
from zk0.deployment.loopback import loopback_federation
from zk0.learning.policy import build_policy
from zk0.learning.rates import compare_text, mcnemar, rate_text

SETTINGS = {  # --setting -> its registry ("" = pyproject.toml's four synthetic owners)
    "mild": "",
    "noniid": str(PROJECT_ROOT / "configs" / "noniid-registry.toml"),  # each owner's own quarter of the table
    "sim-cube": str(PROJECT_ROOT / "configs" / "sim-cube-registry.toml"),  # simulated owners, the cube's xy known
}
CLOSED_LOOP = ("sim-cube",)  # settings whose models are also rolled out in the simulator
RUNS = {  # label -> the run-config keys it adds (the budget's value comes from --budget)
    "fixed steps": {},
    "budget, FedNova": {"averaging": "fednova"},
    "budget, samples": {"averaging": "samples"},
}


def run_config(args, keys: dict, registry: Registry) -> str:
    """One run's keys: the same rounds, steps, batch, learning rate and model for all three (in a
    closed-loop setting, every round's checkpoint kept, to roll out the model of any round)."""
    budget = f" local-time-s={args.budget} round-deadline-s={args.deadline}" if keys else ""
    strings = {**keys, "registry": SETTINGS[args.setting], "model": args.model}
    checkpoint = f"checkpoint-interval={args.rounds}"
    if args.setting in CLOSED_LOOP:
        strings["server-eval-dataset"] = registry.server.name
        checkpoint = "checkpoint-interval=1 keep-checkpoints=0"
    extra = "".join(f" {k}='{v}'" for k, v in strings.items())
    return (
        f"num-server-rounds={args.rounds} local-steps={args.local_steps} batch-size={args.batch_size} lr={args.lr} "
        f"eval-frequency=1 {checkpoint} min-train-clients={args.clients}{budget}{extra}"
    )


def figures_of(history: dict, slow: set[int], budget: float | None) -> dict:
    """A run's round walls, the slow owners' measured slowness and share of steps, MSE by wall time."""
    rounds = history["rounds"]
    walls = {r["round"]: r["wall-s"] for r in rounds}
    last = max(walls)  # its own evaluate message (every client's final evaluation) and the checkpoint
    steady = [walls[r] - walls[r - 1] for r in range(2, last)]
    trained = [
        (int(i), c["train"]) for r in rounds[2:] for i, c in r["clients"].items() if "local-steps" in c.get("train", {})
    ]
    slow_steps = sum(t["local-steps"] for i, t in trained if i in slow)
    step_time = {
        who: statistics.mean(t["step-time"] for i, t in trained if (i in slow) == (who == "slow"))
        for who in ("slow", "others")
    }
    later = [r for r in rounds if 2 <= r["round"] < last]
    return {
        "steady-round-s": steady,
        "mean-steady-round-s": statistics.mean(steady),
        # where a steady round goes: the slowest client's whole answer (its evaluation, catching up
        # and training) and the server's evaluation; the rest is transfers, averaging and artifacts
        "mean-slowest-client-s": statistics.mean(slowest(r)["handler-s"] for r in later),
        "mean-slowest-client-startup-s": statistics.mean(slowest(r).get("startup-s", 0.0) for r in later),
        "mean-server-evaluate-s": statistics.mean(r.get("server-evaluate", {}).get("eval-s", 0.0) for r in later),
        "round-vs-budget": statistics.mean(steady) / budget if budget else None,
        "longest-round-s": max(steady),
        "last-round-s": walls[last] - walls[last - 1],
        "late": {str(r["round"]): r["late"]["clients"] for r in rounds if r.get("late")},
        "slow-owner-step-slowdown": step_time["slow"] / step_time["others"],
        "slow-owner-share-of-steps": slow_steps / sum(t["local-steps"] for _, t in trained),
        "steps-by-client": {
            str(i): [c["train"].get("local-steps") for r in rounds[1:] if (c := r["clients"].get(str(i)))]
            for i in sorted({i for i, _ in trained})
        },  # fmt: skip
        # from the end of round 1: that round builds every client, which takes as long whatever the budget
        "mse-by-wall": [
            (r["wall-s"] - walls[1], r["server-evaluate"]["action-mse"])
            for r in rounds
            if "server-evaluate" in r and r["round"] >= 1
        ],
        "wall-by-round": {str(r): walls[r] - walls[1] for r in sorted(walls) if r >= 1},
        "wall-s": walls[max(walls)],
    }


def slowest(round_row: dict) -> dict:
    """The train metrics of the round's client whose answer took longest (its ``handler-s``)."""
    trained = [c["train"] for c in round_row["clients"].values() if "handler-s" in c.get("train", {})]
    return max(trained, key=lambda t: t["handler-s"], default={"handler-s": 0.0})


def at_wall(mse_by_wall: list[tuple[float, float]], wall: float) -> tuple[float, float]:
    """The model of the last round that had ended by ``wall`` seconds: (its wall time, its MSE)."""
    return [point for point in mse_by_wall if point[0] <= wall][-1]


def closed_loop(args, registry: Registry, folders: dict[str, Path], figures: dict) -> dict:
    """The models the MSE comparison compares, rolled out on the same seeded episodes in the
    server's conditions: {model: its rates and outcomes}, and each budget run against fixed steps
    at equal wall time and at equal rounds."""
    run = RunConfig(registry=SETTINGS[args.setting], server_eval_dataset=registry.server.name, model=args.model)
    entry = registry.get(run.server_eval_dataset)
    meta = open_metadata(entry)
    bundle = build_policy(run, meta, entry, registry.model_cameras())
    split = open_evaluation(entry, meta, bundle.policy.config, run)
    fixed_walls = figures["fixed steps"]["wall-by-round"]
    wanted: dict[str, tuple[str, int]] = {f"fixed steps, round {args.rounds}": ("fixed steps", args.rounds)}
    pairs = {}
    for label in list(RUNS)[1:]:
        wall = figures[label]["wall-by-round"][str(args.rounds)]
        then = max(int(r) for r, w in fixed_walls.items() if w <= wall)  # fixed steps' model by then
        wanted[f"{label}, round {args.rounds}"] = (label, args.rounds)
        wanted[f"fixed steps, round {then}"] = ("fixed steps", then)
        pairs[label] = (
            f"{label}, round {args.rounds}",
            f"fixed steps, round {then}",
            f"fixed steps, round {args.rounds}",
        )
    kept = {label: dict(checkpoints(folder)) for label, folder in folders.items()}  # every round's
    models = {
        name: checkpoint_trainable(kept[label][r], bundle).to_torch_state_dict() for name, (label, r) in wanted.items()
    }
    rolled = closed_loop_all({SERVER: list(models)}, models, {SERVER: (bundle, split, None)},
                             args.sim_episodes, run.seed, lambda line: print(f"  {line}", flush=True))  # fmt: skip
    success = {name: row[SERVER] for name, row in rolled.items()}
    return {
        "success": success,
        "against-fixed": {
            label: {
                "model": mine,
                **{
                    kind: {"model": other, "mcnemar-p": mcnemar(success[mine]["outcomes"], success[other]["outcomes"])}
                    for kind, other in (("equal-wall", at_wall_model), ("equal-rounds", final))
                },
            }
            for label, (mine, at_wall_model, final) in pairs.items()
        },
    }


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench hetero", description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", choices=list(SETTINGS), default="mild", help="the owners' data (as the study's)")
    parser.add_argument("--clients", type=positive(int), default=4)
    parser.add_argument("--slow", type=positive(int), default=1, help="how many owners (the last) are throttled")
    parser.add_argument("--rounds", type=positive(int), default=6)
    parser.add_argument("--local-steps", type=positive(int), default=100)
    parser.add_argument("--budget", type=positive(float), default=10.0, help="local-time-s of the budget runs")
    parser.add_argument("--deadline", type=positive(float), default=30.0, help="round-deadline-s of the budget runs")
    parser.add_argument("--share", type=positive(float), default=0.25, help="the slow owner's share of the CPU")
    parser.add_argument("--batch-size", type=positive(int), default=8)
    parser.add_argument("--lr", type=positive(float), default=2e-3)
    parser.add_argument(
        "--model", default="tiny", choices=OFFLINE_MODELS, help="the offline model (sim-cube: tiny-128)"
    )
    parser.add_argument("--demos", type=positive(int), default=30, help="demonstrations per simulated owner (sim-cube)")
    parser.add_argument(
        "--sim-episodes", type=positive(int), default=100, help="closed-loop episodes per model (sim-cube)"
    )
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.rounds < 3:
        parser.error(
            f"--rounds got {args.rounds}; expected 3 or more (round 1 builds every client, the last evaluates them)"
        )
    if args.share > 1:
        parser.error(f"--share got {args.share}; expected a share of the CPU in (0, 1]")
    registry = load_registry(SETTINGS[args.setting])
    clients = registry.clients[: args.clients]
    if len(clients) < args.clients or args.clients < 2:
        parser.error(f"--clients got {args.clients}; expected 2 to {len(registry.clients)}")
    if args.slow >= args.clients:
        parser.error(f"--slow got {args.slow}; expected fewer than --clients ({args.clients}): someone must be fast")
    supernodes = {f"robot-{i}": entry.name for i, entry in enumerate(clients)}
    slow = set(range(args.clients - args.slow, args.clients))
    figures: dict = {"settings": vars(args), "slow-owners": [f"client {i} ({clients[i].name})" for i in sorted(slow)]}
    with tempfile.TemporaryDirectory(prefix="zk0-bench-hetero-") as tmp:
        root = Path(tmp)
        with native_output_to(root / "assets.log"):  # the owners' data first, as `zk0 assets` makes it
            generate(registry, args.demos)
        folders = {}
        with (
            loopback_federation(root, supernodes, registry=SETTINGS[args.setting]) as fed,
            ExitStack() as throttles,
        ):  # throttles end first
            for i in sorted(slow):
                throttles.enter_context(Throttle(root / f"robot-{i}", args.share))
            for label, keys in RUNS.items():
                out = root / label.replace(", ", "-").replace(" ", "-")
                history = fed.run_history(
                    run_config(args, keys, registry), out, f"bench.hetero ({label})", timeout=3600
                )
                if history is None:
                    return 1
                folders[label] = Path(history["run-dir"])
                figures[label] = figures_of(history, slow, args.budget if keys else None)
                print(f"  {label}: {figures[label]['wall-s']:.0f} s", flush=True)
        if args.setting in CLOSED_LOOP:  # after the runs: the throttles are off, nothing else runs
            figures["closed-loop"] = closed_loop(args, registry, folders, figures)
    report(figures, args)
    write_json(args.json, figures)
    return 0


def report(figures: dict, args) -> None:
    """The table, and each budget run against fixed steps at its own wall time."""
    fixed = figures["fixed steps"]
    print(f"\n{args.clients} {args.setting} owners, {', '.join(figures['slow-owners'])} held to {args.share:.0%} of the CPU; "
          f"{args.rounds} rounds of {args.local_steps} steps or local-time-s={args.budget:g} "
          f"(round-deadline-s={args.deadline:g}), batch {args.batch_size}, lr {args.lr:g}")  # fmt: skip
    print(f"{'':<16}{'round s':>9}{'longest':>9}{'x budget':>10}{'slow step':>11}{'slow share':>12}"
          f"{'final MSE':>11}{'wall s':>8}")  # fmt: skip
    for label in RUNS:
        f = figures[label]
        ratio = "-" if f["round-vs-budget"] is None else f"{f['round-vs-budget']:.2f}"
        print(f"{label:<16}{f['mean-steady-round-s']:>9.1f}{f['longest-round-s']:>9.1f}{ratio:>10}"
              f"{f['slow-owner-step-slowdown']:>10.1f}x{f['slow-owner-share-of-steps']:>12.1%}"
              f"{f['mse-by-wall'][-1][1]:>11.4g}{f['wall-s']:>8.0f}")  # fmt: skip
        print(f"{'':<16}a round: the slowest client's answer {f['mean-slowest-client-s']:.1f} s (its ClientApp "
              f"process started {f['mean-slowest-client-startup-s']:.1f} s before), the server's evaluation "
              f"{f['mean-server-evaluate-s']:.1f} s; the last round {f['last-round-s']:.1f} s")  # fmt: skip
        for round_number, late in f["late"].items():
            print(f"  round {round_number}: late, dropped: {', '.join(f'client {i}' for i in late)}")
    for label in list(RUNS)[1:]:
        f = figures[label]
        wall, mse = f["mse-by-wall"][-1]
        then, fixed_mse = at_wall(fixed["mse-by-wall"], wall)
        f["vs-fixed-at-equal-wall"] = mse / fixed_mse
        print(f"{label} {wall:.0f} s after round 1: server action MSE {mse:.4g} against fixed steps' {fixed_mse:.4g} "
              f"(its model at {then:.0f} s): {mse / fixed_mse:.2f}x")  # fmt: skip
    if "closed-loop" in figures:
        report_closed_loop(figures["closed-loop"])


def report_closed_loop(closed: dict) -> None:
    """Each rolled-out model's success with its interval, and each budget run against fixed steps."""
    success = closed["success"]
    print("closed-loop success in the server's conditions:")
    for name, rates in success.items():
        print(f"  {name:<28}{rate_text(rates['success-rate'], int(rates['episodes']))}")
    for against in closed["against-fixed"].values():
        mine = success[against["model"]]["outcomes"]
        for kind in ("equal-wall", "equal-rounds"):
            other = against[kind]["model"]
            text = compare_text(mine, success[other]["outcomes"])
            print(f"  {against['model']} against {other} ({kind.replace('-', ' ')}): {text}")


if __name__ == "__main__":
    sys.exit(main())
