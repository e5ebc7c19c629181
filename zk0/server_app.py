"""zk0 ServerApp: FedProx over the trainable SmolVLA parameters, server evaluation, artifacts.

The server builds the global policy exactly as clients do (same base, same seed) on
its evaluation dataset, sends only the trainable arrays plus the backbone fingerprint,
aggregates the clients' updates weighted by samples trained, and at the end of every
round evaluates the global model (every ``eval-frequency`` rounds) and writes JSON,
charts and, every ``checkpoint-interval`` rounds and after the last, a checkpoint.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from flwr.app import ArrayRecord, ConfigRecord, Context, MetricRecord, RecordDict
from flwr.serverapp import Grid, ServerApp
from lerobot.datasets.compute_stats import aggregate_stats
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.policies import make_pre_post_processors
from loguru import logger

from zk0 import app_fingerprint
from zk0.aggregation import ValidatingFedProx, array_signature
from zk0.artifacts import History, new_run_dir, save_checkpoint, write_json
from zk0.config import RunConfig, from_run_config
from zk0.data import DataError, DatasetSplit, eval_loader, open_evaluation
from zk0.errors import Zk0Error
from zk0.grid import PromptGrid
from zk0.hub import can_push, publish
from zk0.internals import is_simulation
from zk0.logs import add_file_sink, setup_logging
from zk0.policy import PolicyBundle, backbone_fingerprint, build_policy, get_trainable, set_trainable
from zk0.preflight import SIZED, check_federation
from zk0.registry import Registry, load_registry
from zk0.resume import ResumePoint, find_resume_point
from zk0.stats import stats_from_record
from zk0.tracking import Tracker
from zk0.training import evaluate
from zk0.wire import SHAPE

app = ServerApp()


class RoundEnd:
    """Flower's ``evaluate_fn`` hook, the last step of every round: server eval, then artifacts."""

    def __init__(
        self,
        run: RunConfig,
        registry: Registry,
        bundle: PolicyBundle,
        split: DatasetSplit,
        history: History,
        tracker: Tracker,
        resumed: ResumePoint | None,
    ):
        self.run, self.registry, self.bundle, self.split = run, registry, bundle, split
        self.history, self.tracker = history, tracker
        self.push = can_push(run)
        self.loader = eval_loader(split.evaluation, run)
        self.round_offset = resumed.round if resumed else 0
        self.client_stats: dict[int, dict] = dict(resumed.client_stats) if resumed else {}
        self.started = time.perf_counter()

    def record_clients(
        self,
        phase: str,
        server_round: int,
        replies: list[RecordDict],
        aggregate: MetricRecord | None,
        failures: dict[int, str],
    ) -> None:
        """Keep each client's metrics (by dataset index, never node id), their aggregate, dataset
        statistics, and why a client's reply failed (``failures``: dataset index -> reason)."""
        for index, reason in failures.items():
            self.history.add_client(server_round, phase, index, {"error": reason})
        if aggregate:
            summary = {k: v for k, v in aggregate.items() if k != "dataset-index"}
            self.history.add(server_round, f"aggregate-{phase}", summary)
        for content in replies:
            metrics = dict(content["metrics"])
            index = int(metrics.pop("dataset-index"))
            self.history.add_client(server_round, phase, index, metrics)
            if "stats" in content:
                self.client_stats[index] = stats_from_record(content["stats"])

    def __call__(self, server_round: int, arrays: ArrayRecord) -> MetricRecord | None:
        if server_round == 0 and self.round_offset:
            return None  # a resumed run's starting model is its last checkpoint, already evaluated
        server_round += self.round_offset
        set_trainable(self.bundle, arrays)
        self.history.add(server_round, "global-arrays", {"tensors": len(arrays), "bytes": arrays.count_bytes()})
        metrics = None
        if server_round == 0 or self.run.evaluates_in(server_round):
            run = self.run
            metrics = evaluate(self.bundle, self.split, self.loader, run.eval_batches, run.seed, run.max_skip_fraction)
            logger.info("Round {} server evaluation on {}: {}", server_round, self.split.entry.name, metrics)
            self.history.add(server_round, "server-evaluate", metrics)
        self.history.add(server_round, "wall-s", time.perf_counter() - self.started)
        self.history.write_round(server_round)
        if server_round and (
            server_round % self.run.checkpoint_interval == 0 or server_round == self.run.num_server_rounds
        ):
            per_client = {
                f"client_{i}_{self.history.client_names[i]}": st for i, st in sorted(self.client_stats.items())
            }
            path = save_checkpoint(self.checkpoint_bundle(), self.history.run_dir, server_round, per_client)
            logger.info("Round {} checkpoint: {}", server_round, path)
            if self.run.hf_repo_id and (
                self.run.hf_push_every_checkpoint or server_round == self.run.num_server_rounds
            ):
                entries = [self.registry.get(n) for n in self.history.participants().values()] + [self.split.entry]
                publish(self.run, self.history.run_dir, path, server_round, entries, metrics, self.push)
        self.tracker.log(server_round, self.history.round(server_round))
        return MetricRecord(metrics) if metrics else None

    def checkpoint_bundle(self) -> PolicyBundle:
        """The global policy with processors carrying the clients' merged statistics (lerobot's aggregation)."""
        stats = aggregate_stats(list(self.client_stats.values())) if self.client_stats else self.bundle.stats
        pre, post = make_pre_post_processors(self.bundle.policy.config, dataset_stats=stats)
        return PolicyBundle(self.bundle.policy, pre, post, self.bundle.trainable_names, self.bundle.device, stats)


def record_run_config(run: RunConfig, run_dir: Path, resumed: ResumePoint | None) -> None:
    """Keep the run config with the run; a resumed run says which settings changed."""
    path = run_dir / "server" / "run_config.json"
    if resumed:
        logger.info("Resuming {} after round {} (checkpoint {})", run_dir, resumed.round, resumed.checkpoint.name)
        before = json.loads(path.read_text()) if path.is_file() else {}
        changed = {k: (before.get(k), v) for k, v in run.to_flat().items() if k != "resume-from" and before.get(k) != v}
        if changed:
            logger.warning("The resumed run differs from the original in {}", changed)
    else:
        logger.info("Writing to {}", run_dir)
    write_json(path, run.to_flat())


def preflight(run: RunConfig, registry: Registry, simulation: bool) -> LeRobotDatasetMetadata:
    """Refuse unusable datasets before round 1, each in its own sentence; the server dataset's metadata.

    In a simulation every client's dataset is on this machine and is checked here; in a
    deployment each SuperNode checks its own (``zk0 supernode``, and its client on opening it).
    """
    report = check_federation(run, registry, clients=simulation, skip_absent=False)
    for problem in report.problems:
        logger.error("zk0: {}", problem)
    if report.problems:
        raise DataError(
            f"{len(report.problems)} dataset(s) of this federation cannot be used (above); nothing trained."
        )
    return report.server_meta


@app.main()
def main(grid: Grid, context: Context) -> None:
    """Validate the config and every local dataset, build the global model, run FedProx, write
    artifacts every round."""
    setup_logging("server")
    try:
        run = from_run_config(dict(context.run_config))
        registry = load_registry(run.registry)
        resumed = find_resume_point(run.resume_from) if run.resume_from else None
        meta = preflight(run, registry, simulation=is_simulation(grid))
        run_dir = resumed.run_dir if resumed else new_run_dir(run.output_dir)
    except Zk0Error as err:
        logger.error("zk0: {}", err)  # the one sentence, before Flower's own report of the failure
        raise
    entry = registry.get(run.server_eval_dataset)
    add_file_sink(run_dir / "server" / "server.log", "server")
    record_run_config(run, run_dir, resumed)
    done = resumed.round if resumed else 0
    if done >= run.num_server_rounds:
        logger.info(
            "{} already has round {} of num-server-rounds={}; nothing to do.", run_dir, done, run.num_server_rounds
        )
        return

    bundle = build_policy(run, meta, entry, registry.model_cameras())
    initial = resumed.trainable(bundle) if resumed else get_trainable(bundle)
    fingerprint = backbone_fingerprint(bundle)
    logger.info(
        "Global model: {} trainable tensors, backbone fingerprint {}; app {}",
        len(initial),
        fingerprint,
        app_fingerprint(),
    )

    history = History(
        run_dir, {i: e.name for i, e in enumerate(registry.clients)}, dict(resumed.rounds) if resumed else {}
    )
    tracker = Tracker.start(run, run_dir)
    split = open_evaluation(entry, meta, bundle.policy.config, run)
    round_end = RoundEnd(run, registry, bundle, split, history, tracker, resumed)
    strategy = ValidatingFedProx(
        expected=array_signature(initial),
        evaluates_in=run.evaluates_in,
        recorder=round_end.record_clients,
        last_round=run.num_server_rounds,
        proximal_mu=run.proximal_mu,
        fraction_train=run.fraction_train,
        fraction_evaluate=run.fraction_evaluate,
        min_train_nodes=run.min_train_clients,
        min_evaluate_nodes=1,
        min_available_nodes=run.min_train_clients,
        round_offset=done,
        wire_dtype=run.wire_dtype,
    )
    # The run's folder name (clients keep their logs under a folder of that name on their own
    # machine, never at a path of the server's) and what both ends must share.
    shared = {
        "backbone-fingerprint": fingerprint,
        "app-fingerprint": app_fingerprint(),
        "run-name": run_dir.name,
        **{SHAPE + key: list(ft.shape) for key, ft in model_features(bundle).items() if key in SIZED},
    }
    try:
        strategy.start(
            grid=PromptGrid(grid),
            initial_arrays=initial,
            num_rounds=run.num_server_rounds - done,
            train_config=ConfigRecord(dict(shared)),
            evaluate_config=ConfigRecord(dict(shared)),
            evaluate_fn=round_end,
        )
    except Zk0Error as err:
        logger.error("zk0: {}", err)
        raise
    finally:
        tracker.finish()
    logger.info("Done: outputs in {}", run_dir)


def model_features(bundle: PolicyBundle) -> dict:
    """The global policy's input and output features (what every client's dataset must match)."""
    return {**bundle.policy.config.input_features, **bundle.policy.config.output_features}
