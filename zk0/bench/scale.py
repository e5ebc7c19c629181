"""Scale benchmark: what 4, 16 and 64 owners cost a simulated federation.

For each ``--owners`` N: N synthetic owners from one registry table (``[tool.zk0.owners]``,
written to the output folder), their datasets generated first (timed apart: on a real
federation each owner generates or records its own, once), then ``flwr run`` with N
SuperNodes of which ``--per-round`` are sampled to train and to evaluate each round
(``fraction-train = fraction-evaluate = per-round / N``), the tiny model, ``--rounds`` rounds
of ``--local-steps``. Measured from outside the run, as a user would: start-up (``flwr run``
until round 1 begins: the SuperLink, the simulation's N SuperNodes and Ray, the ServerApp's
model and its evaluation of the initial model), the wall time of every round, and resident
memory sampled every half second: the server side (the SuperLink, its SuperExec, and the
simulation process: the ServerApp and the engine that holds the N nodes) and the largest client process (a Ray actor running
ClientApps for whichever owners it is given). Then how each grows with N: the steady round
against the first N's, and the server side's memory per registered owner.

    python -m zk0.bench scale [--owners 4 16 64] [--per-round 4] [--rounds 3] [--local-steps 5]
        [--output-dir outputs/bench-scale] [--json FILE]
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

from zk0.artifacts.logs import native_output_to
from zk0.bench.client import write_json
from zk0.bench.watch import Watch
from zk0.common.errors import OneSentenceParser, positive
from zk0.data.assets import ensure_dataset
from zk0.data.registry import load_registry
from zk0.deployment.simulation import run_federation


def owners_registry(folder: Path, owners: int) -> Path:
    """The one-table registry of ``owners`` synthetic owners."""
    path = folder / f"owners-{owners}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f'[tool.zk0.owners]\ncount = {owners}\nkind = "synth"\n')
    return path


def measure(args, owners: int) -> dict | None:
    """One federation of ``owners`` owners: its start-up, round walls and memory."""
    out = Path(args.output_dir).resolve() / f"owners-{owners}"
    registry = owners_registry(out, owners)
    started = time.perf_counter()
    with native_output_to(out / "assets.log"):  # FFmpeg's muxer lines, as `zk0 assets` keeps them
        for entry in load_registry(registry).entries:
            ensure_dataset(entry.name)
    assets_s = time.perf_counter() - started
    share = min(1.0, args.per_round / owners)
    run_config = (
        f"registry='{registry}' num-server-rounds={args.rounds} local-steps={args.local_steps} "
        f"fraction-train={share} fraction-evaluate={share} min-train-clients={min(args.per_round, owners)} "
        f"eval-frequency=1 checkpoint-interval={args.rounds}"
    )
    watch = Watch(out)
    started = time.perf_counter()
    history = run_federation(run_config, owners, out, f"bench.scale ({owners} owners)", watch=watch.during)
    if history is None:
        return None
    walls = {r["round"]: r["wall-s"] for r in history["rounds"]}
    rounds = [walls[r] - walls[r - 1] for r in range(1, max(walls) + 1)]
    start = watch.recorded_at.get(0)  # round 0: the initial model evaluated; round 1 starts then
    return {
        "owners": owners,
        "trained-per-round": [len([c for c in r["clients"].values() if "train" in c]) for r in history["rounds"][1:]],
        "assets-s": assets_s,
        "start-up-s": start,
        "round-s": rounds,
        "steady-round-s": statistics.mean(rounds[1:]) if len(rounds) > 1 else rounds[0],
        "flwr-run-s": time.perf_counter() - started,
        "peak-mib": watch.peak_mib,
        "client-process-peak-mib": watch.client_process_mib,
        "run-dir": history["run-dir"],
    }


def growth(rows: list[dict]) -> dict:
    """How the largest N compares with the smallest: round time as a ratio, server memory per owner."""
    small, large = rows[0], rows[-1]
    added = large["owners"] - small["owners"]
    return {
        "from": small["owners"],
        "to": large["owners"],
        "steady-round-ratio": large["steady-round-s"] / small["steady-round-s"],
        "server-mib-per-owner": (large["peak-mib"]["server side"] - small["peak-mib"]["server side"]) / added,
        "client-process-mib-per-owner": (large["client-process-peak-mib"] - small["client-process-peak-mib"]) / added,
    }


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench scale", description=__doc__.split("\n\n")[0])
    parser.add_argument("--owners", type=positive(int), nargs="+", default=[4, 16, 64])
    parser.add_argument("--per-round", type=positive(int), default=4, help="owners sampled to train each round")
    parser.add_argument("--rounds", type=positive(int), default=3)
    parser.add_argument("--local-steps", type=positive(int), default=5)
    parser.add_argument("--output-dir", default="outputs/bench-scale")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    owners = sorted(set(args.owners))
    if owners[0] < 2:
        parser.error(f"--owners got {owners[0]}; expected 2 or more owners in each federation")
    if args.rounds < 2:
        parser.error(f"--rounds got {args.rounds}; expected 2 or more (round 1 builds the first clients)")
    rows = []
    for n in owners:
        row = measure(args, n)
        if row is None:
            return 1
        rows.append(row)
        print(f"  {n} owners: {row['flwr-run-s']:.0f} s", flush=True)
    figures = {"settings": vars(args), "owners": rows, "growth": growth(rows) if len(rows) > 1 else None}
    report(figures, args)
    write_json(args.json, figures)
    return 0


def report(figures: dict, args) -> None:
    """One line per N, then the growth from the smallest to the largest."""
    print(f"\nsynthetic owners, {args.per_round} sampled to train and evaluate a round, tiny model, "
          f"{args.rounds} rounds of {args.local_steps} steps")  # fmt: skip
    print(f"{'owners':>7}{'assets s':>10}{'start-up s':>12}{'round 1 s':>11}{'steady s':>10}"
          f"{'server MiB':>12}{'client MiB':>12}{'Ray MiB':>9}")  # fmt: skip
    for row in figures["owners"]:
        peak = row["peak-mib"]
        start = "-" if row["start-up-s"] is None else f"{row['start-up-s']:.1f}"
        print(f"{row['owners']:>7}{row['assets-s']:>10.1f}{start:>12}{row['round-s'][0]:>11.1f}"
              f"{row['steady-round-s']:>10.1f}{peak.get('server side', 0):>12.0f}"
              f"{row['client-process-peak-mib']:>12.0f}{peak.get('ray', 0):>9.0f}")  # fmt: skip
    if g := figures["growth"]:
        print(f"{g['from']} -> {g['to']} owners: steady round {g['steady-round-ratio']:.2f}x, server side "
              f"{g['server-mib-per-owner']:+.1f} MiB per owner, a client process {g['client-process-mib-per-owner']:+.1f} MiB per owner")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
