"""Soak benchmark: does a long run stay flat? Memory, open files, threads and disk over many rounds.

One federation of ``--rounds`` rounds (the tiny model, ``--clients`` clients, a few local steps, a
checkpoint every ``--checkpoint-interval`` rounds with ``keep-checkpoints``' default), run with
``flwr run`` as a user runs it: in simulation, or with ``--deployment`` on a loopback Deployment
Engine (zk0.deployment.loopback: a TLS SuperLink and one ``zk0 supernode`` per client). Watched from outside
(zk0.bench.watch): at the end of every round the server side's resident memory (the SuperLink, its
SuperExec, the process that runs the ServerApp), each client process's (a Ray actor, or a
SuperNode's warm worker), the SuperNodes' own, their open file descriptors and threads, and the
output folder's size. Reported: each one's growth from round ``--from-round`` (after start-up and
the first checkpoints) to the last, against the targets (memory under 5%, descriptors and threads
not growing, the folder flat once the kept checkpoints are there); JSON and a chart.

    python -m zk0.bench soak [--rounds 200] [--clients 2] [--local-steps 2] [--checkpoint-interval 10]
        [--from-round 10] [--deployment] [--output-dir outputs/bench-soak] [--json FILE] [--chart FILE]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from matplotlib.figure import Figure

from zk0.bench.client import write_json
from zk0.bench.watch import Watch
from zk0.common.errors import OneSentenceParser, positive
from zk0.data.registry import load_registry
from zk0.deployment.loopback import loopback_federation
from zk0.deployment.simulation import run_federation


def growth(rows: list[dict], start: int) -> dict:
    """From round ``start``'s row to the last: memory as a fraction, descriptors and threads as counts."""
    first = next(r for r in rows if r["round"] >= start)
    last = rows[-1]
    clients = sorted(set(first["client-processes-mib"]) & set(last["client-processes-mib"]))
    return {
        "from-round": first["round"],
        "to-round": last["round"],
        "server-side-memory": last["mib"]["server side"] / first["mib"]["server side"] - 1,
        **(
            {"supernode-memory": last["mib"]["supernode"] / first["mib"]["supernode"] - 1}
            if "supernode" in first["mib"] and "supernode" in last["mib"]
            else {}
        ),
        "client-process-memory": {
            pid: last["client-processes-mib"][pid] / first["client-processes-mib"][pid] - 1 for pid in clients
        },
        "server-fds": last["server-fds"] - first["server-fds"],
        "server-threads": last["server-threads"] - first["server-threads"],
        "client-fds": last["client-fds"] - first["client-fds"],
        "client-threads": last["client-threads"] - first["client-threads"],
        "output-bytes": last["output-bytes"] - first["output-bytes"],
    }


def chart(rows: list[dict], path: Path) -> None:
    """Resident memory by process and the output folder's size, round by round."""
    fig = Figure(figsize=(8, 6))
    memory, disk = fig.subplots(2, 1, sharex=True)
    rounds = [r["round"] for r in rows]
    memory.plot(rounds, [r["mib"]["server side"] for r in rows], label="server side")
    for pid in sorted({p for r in rows for p in r["client-processes-mib"]}):
        memory.plot(rounds, [r["client-processes-mib"].get(pid) for r in rows], label=f"client process {pid}")
    memory.set(ylabel="resident MiB", title="memory and disk over the run")
    memory.legend(fontsize=8)
    disk.plot(rounds, [r["output-bytes"] / 2**20 for r in rows])
    disk.set(xlabel="round", ylabel="output folder MiB")
    for axis in (memory, disk):
        axis.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=positive(int), default=200)
    parser.add_argument("--clients", type=positive(int), default=2)
    parser.add_argument("--local-steps", type=positive(int), default=2)
    parser.add_argument("--checkpoint-interval", type=positive(int), default=10)
    parser.add_argument("--from-round", type=positive(int), default=10, help="growth is measured from this round")
    parser.add_argument("--deployment", action="store_true", help="on a loopback Deployment Engine, a SuperNode each")
    parser.add_argument("--output-dir", default="outputs/bench-soak")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    parser.add_argument("--chart", help="the PNG chart (default: <output-dir>/soak.png)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.from_round >= args.rounds:
        parser.error(f"--from-round got {args.from_round}; expected a round before the last ({args.rounds})")
    out = Path(args.output_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_config = (
        f"num-server-rounds={args.rounds} local-steps={args.local_steps} batch-size=4 eval-batches=1 "
        f"checkpoint-interval={args.checkpoint_interval} min-train-clients={args.clients}"
    )
    watch = Watch(out)
    run = deployed if args.deployment else simulated
    if not run(run_config, args.clients, out, watch):
        return 1
    figures = {"settings": vars(args), "rounds": watch.rounds, "growth": growth(watch.rounds, args.from_round)}
    report(figures["growth"], watch.rounds)
    chart(watch.rounds, Path(args.chart or out / "soak.png"))
    write_json(args.json, figures)
    return 0


def simulated(run_config: str, clients: int, out: Path, watch: Watch) -> bool:
    """The run in the Simulation Engine, as ``./train.sh`` runs it."""
    return run_federation(run_config, clients, out, "bench.soak", watch=watch.during) is not None


def deployed(run_config: str, clients: int, out: Path, watch: Watch) -> bool:
    """The run on a loopback Deployment Engine, a SuperNode (and its warm worker) per client."""
    supernodes = {f"robot-{i}": entry.name for i, entry in enumerate(load_registry().clients[:clients])}
    with (
        tempfile.TemporaryDirectory(prefix="zk0-bench-soak-") as tmp,
        loopback_federation(Path(tmp), supernodes) as fed,
    ):
        with watch.around(fed.process_tree):
            return fed.run_history(run_config, out, "bench.soak", timeout=24 * 3600) is not None


def report(g: dict, rows: list[dict]) -> None:
    """Each figure against its target."""
    last = rows[-1]
    print(f"\nrounds {g['from-round']} -> {g['to-round']} ({last['s']:.0f} s in all):")
    print(f"  server side memory {last['mib']['server side']:.0f} MiB: {g['server-side-memory']:+.1%} (target < +5%)")
    if "supernode-memory" in g:
        print(f"  SuperNodes {last['mib']['supernode']:.0f} MiB: {g['supernode-memory']:+.1%} (target < +5%)")
    for pid, change in g["client-process-memory"].items():
        print(f"  client process {pid} {last['client-processes-mib'][pid]:.0f} MiB: {change:+.1%} (target < +5%)")
    print(f"  open files: server side {g['server-fds']:+d}, clients {g['client-fds']:+d}; threads: server side "
          f"{g['server-threads']:+d}, clients {g['client-threads']:+d} (target: no growth)")  # fmt: skip
    print(f"  output folder {last['output-bytes'] / 2**20:.1f} MiB: {g['output-bytes'] / 2**20:+.1f} MiB")


if __name__ == "__main__":
    sys.exit(main())
