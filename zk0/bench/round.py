"""Round benchmark: how much of a round is local training, and how much is everything else.

Runs the real app (`flwr run` on a private local SuperLink) for two rounds of ``--local-steps``
with ``--clients`` clients and reads the server's history: round 2 is the steady state (round 1
also builds each client's policy and opens its dataset). Everything but the clients' local
steps is the overhead; it is split into evaluation on the clients and on the server (which
``eval-frequency`` thins out) and the rest: receive and deserialise, load weights, serialise,
aggregate, checkpoint, charts, Flower's scheduling.

    python -m zk0.bench round [--local-steps 200] [--clients 1] [--model tiny] [--json out.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from zk0.common.errors import OneSentenceParser
from zk0.deployment.simulation import run_federation


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench round", description=__doc__.split("\n\n")[0])
    parser.add_argument("--local-steps", type=int, default=200)
    parser.add_argument("--clients", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--model", default="tiny", help="tiny, full-size, or a SmolVLA checkpoint")
    parser.add_argument("--output-dir", default="outputs/bench-round")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    run_config = (
        f"num-server-rounds=2 local-steps={args.local_steps} batch-size={args.batch_size} model='{args.model}' "
        f"min-train-clients={args.clients} checkpoint-interval=1"
    )
    history = run_federation(run_config, args.clients, Path(args.output_dir).resolve(), "bench.round")
    if history is None:
        return 1
    rounds = {r["round"]: r for r in history["rounds"]}
    wall = rounds[2]["wall-s"] - rounds[1]["wall-s"]
    clients = rounds[2]["clients"].values()
    train = max(c["train"]["step-time"] * args.local_steps for c in clients)  # the slowest client gates the round
    overhead = wall - train
    client_eval = max(c["evaluate"]["eval-s"] for c in clients)
    server_eval = rounds[2]["server-evaluate"]["eval-s"]
    figures = {
        "round-wall-s": wall,
        "local-steps-s": train,
        "overhead-s": overhead,
        "overhead-fraction": overhead / wall,
        "client-evaluation-s": client_eval,
        "server-evaluation-s": server_eval,
        "rest-s": overhead - client_eval - server_eval,
        "peak-gpu-gib": max(c["train"]["peak-gpu-gib"] for c in clients),
        "host-rss-gib": max(c["train"]["host-rss-gib"] for c in clients),
        "first-round-wall-s": rounds[1]["wall-s"] - rounds[0]["wall-s"],
    }
    print(f"model {args.model}, {args.clients} client(s), {args.local_steps} local steps, batch {args.batch_size}")
    print(
        f"round 2 (steady state): {wall:.2f} s = {train:.2f} s local steps + {overhead:.2f} s else "
        f"({100 * figures['overhead-fraction']:.1f}% overhead)"
    )
    print(
        f"  overhead: {client_eval:.2f} s client evaluation + {server_eval:.2f} s server evaluation + "
        f"{figures['rest-s']:.2f} s messages, aggregation, checkpoint, charts ({100 * figures['rest-s'] / wall:.1f}%)"
    )
    print(f"round 1 (builds policy and data): {figures['first-round-wall-s']:.2f} s")
    print(f"per client: peak GPU {figures['peak-gpu-gib']:.2f} GiB, host RSS {figures['host-rss-gib']:.2f} GiB")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
