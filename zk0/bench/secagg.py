"""SecAgg: what Flower's own SecAgg+ costs at zk0's update sizes, and the dropouts it survives.

zk0's apps cannot put their updates through Flower 1.42's SecAgg+: it exists only in Flower's
legacy workflow (``LegacyContext``, a legacy ``Strategy``, ``FitRes`` replies), which zk0's
Message-API strategy stack does not use (docs/privacy.md). This measures the protocol itself,
unmodified, on Flower's legacy apps as Flower's ``flower-secure-aggregation`` example builds
them: each of ``--owners`` clients answers one round with float32 arrays of an update's size
(``--sizes-mb``: 0.76 = a LoRA update, 200 = a full-size bf16 update's bytes), through
Flower's Simulation Engine, with and without ``SecAggPlusWorkflow``. It reports

- the round's wall time with SecAgg+ and without (the same legacy round), and their ratio;
- the bytes each client sent in the round with SecAgg+ (every stage's reply, as Flower counts
  its records) against its plain update;
- with ``--drop`` k: whether the round still completes when k clients fail at the stage
  where they send their masked vectors (their masks are then rebuilt from the others' shares),
  for k from 1 up to the first k that breaks it.

Every client shares with every other (``num_shares`` = owners) and the reconstruction
threshold is ``--threshold`` of them (Flower's example uses about two thirds).

    python -m zk0.bench secagg [--owners 4 16] [--sizes-mb 0.76 200] [--threshold 0.67] [--drop]
        [--json FILE]
"""

from __future__ import annotations

import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from flwr.client import NumPyClient
from flwr.client.mod import secaggplus_mod
from flwr.clientapp import ClientApp
from flwr.common import ndarrays_to_parameters
from flwr.server import LegacyContext, ServerConfig
from flwr.server.strategy import FedAvg
from flwr.server.workflow import DefaultWorkflow, SecAggPlusWorkflow
from flwr.serverapp import ServerApp
from flwr.simulation import run_simulation

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser, positive

MIB = 2**20


class Update(NumPyClient):
    """A client whose update is ``values`` random float32 weights; it fails when ``fails``."""

    def __init__(self, values: int, seed: int, fails: bool):
        self.values, self.seed, self.fails = values, seed, fails

    def fit(self, parameters, config):
        if self.fails:
            raise RuntimeError("this client drops out at the masked-vector stage")
        update = np.random.default_rng(self.seed).uniform(-1, 1, self.values).astype(np.float32)
        return [update], 1, {}


def client_app(values: int, drops: int, ledger: Path, secure: bool) -> ClientApp:
    """Flower's legacy ClientApp answering with an update of ``values`` weights; its first ``drops``
    clients fail. A mod outside SecAgg+'s writes the bytes of every reply it sends to ``ledger``."""

    def client_fn(context):
        partition = int(context.node_config["partition-id"])
        return Update(values, partition, fails=partition < drops).to_client()

    def count_sent(msg, context, call_next):
        reply = call_next(msg, context)
        if not reply.has_error():
            sent = sum(record.count_bytes() for record in reply.content.values())
            with ledger.open("a") as out:
                out.write(f"{context.node_config['partition-id']} {sent}\n")
        return reply

    return ClientApp(client_fn=client_fn, mods=[count_sent, secaggplus_mod] if secure else [count_sent])


def server_app(values: int, owners: int, threshold: float, secure: bool, result: dict) -> ServerApp:
    """Flower's legacy ServerApp for one round over ``owners`` clients, as Flower's example builds it;
    ``result`` gets the round's wall time and whether it produced an aggregate."""
    app = ServerApp()

    @app.main()
    def main(grid, context) -> None:
        start = ndarrays_to_parameters([np.zeros(values, dtype=np.float32)])
        strategy = FedAvg(
            fraction_fit=1.0, fraction_evaluate=0.0, min_fit_clients=owners, min_available_clients=owners,
            initial_parameters=start,
        )  # fmt: skip
        aggregated = {}

        def keep(server_round, results, failures):
            aggregated["clients"], aggregated["failures"] = len(results), len(failures)
            return FedAvg.aggregate_fit(strategy, server_round, results, failures)

        strategy.aggregate_fit = keep
        legacy = LegacyContext(context=context, config=ServerConfig(num_rounds=1), strategy=strategy)
        fit = (
            SecAggPlusWorkflow(num_shares=owners, reconstruction_threshold=threshold, max_weight=1, timeout=600)
            if secure
            else None
        )
        workflow = DefaultWorkflow(fit_workflow=fit) if secure else DefaultWorkflow()
        began = time.perf_counter()
        workflow(grid, legacy)
        result["round-s"] = time.perf_counter() - began
        result["aggregated"] = aggregated.get("clients", 0)

    return app


def one_round(values: int, owners: int, threshold: float, secure: bool, drops: int = 0) -> dict:
    """One simulated round: its wall time, whether it aggregated, and each client's bytes sent."""
    result: dict = {}
    with tempfile.TemporaryDirectory(prefix="zk0-bench-secagg-") as tmp:
        ledger = Path(tmp) / "sent.txt"
        ledger.touch()
        run_simulation(
            server_app(values, owners, threshold, secure, result),
            client_app(values, drops, ledger, secure),
            num_supernodes=owners,
            backend_config={"client_resources": {"num_cpus": 2 / owners}, "init_args": {"num_cpus": 2}},
        )
        sent: dict[str, int] = {}
        for line in ledger.read_text().split("\n"):
            if line:
                node, size = line.split()
                sent[node] = sent.get(node, 0) + int(size)
    result["sent-bytes-per-client"] = max(sent.values(), default=0)
    return result


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench secagg", description=__doc__.split("\n\n")[0])
    parser.add_argument("--owners", type=positive(int), nargs="+", default=[4, 16])
    parser.add_argument("--sizes-mb", type=positive(float), nargs="+", default=[0.76, 200.0])
    parser.add_argument("--threshold", type=positive(float), default=0.67, help="share of the owners, or a count")
    parser.add_argument("--drop", action="store_true", help="also find how many dropouts a round survives")
    parser.add_argument("--json", default=None)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if min(args.owners) < 3:
        parser.error(f"--owners got {min(args.owners)}; expected 3 or more (SecAgg+ needs a threshold of 2)")
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    logging.getLogger("flwr").setLevel(logging.WARNING)
    figures: dict = {"settings": vars(args), "rounds": []}
    for owners in args.owners:
        for size in args.sizes_mb:
            values = int(size * MIB / 4)
            plain = one_round(values, owners, args.threshold, secure=False)
            secure = one_round(values, owners, args.threshold, secure=True)
            row = {
                "owners": owners,
                "update-mb": size,
                "plain-round-s": plain["round-s"],
                "secagg-round-s": secure["round-s"],
                "time-ratio": secure["round-s"] / plain["round-s"],
                "plain-sent-mb": plain["sent-bytes-per-client"] / MIB,
                "secagg-sent-mb": secure["sent-bytes-per-client"] / MIB,
                "aggregated": secure["aggregated"],
            }
            if args.drop:
                row["survives-drops"] = survived(values, owners, args.threshold)
            figures["rounds"].append(row)
            print(
                f"{owners:>3} owners, {size:g} MB update: round {plain['round-s']:.1f} s plain, "
                f"{secure['round-s']:.1f} s with SecAgg+ ({row['time-ratio']:.1f}x); each client sent "
                f"{row['plain-sent-mb']:.2f} MB plain, {row['secagg-sent-mb']:.2f} MB with SecAgg+"
                + (f"; survives {row['survives-drops']} dropout(s)" if args.drop else ""),
                flush=True,
            )
    write_json(args.json, figures)
    return 0


def survived(values: int, owners: int, threshold: float) -> int:
    """The most clients that may fail at the masked-vector stage with the round still aggregating."""
    drops = 0
    while drops + 1 < owners and one_round(values, owners, threshold, secure=True, drops=drops + 1)["aggregated"]:
        drops += 1
    return drops


if __name__ == "__main__":
    sys.exit(main())
