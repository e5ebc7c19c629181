"""zk0 ServerApp: federated averaging of the trainable SmolVLA parameters, server evaluation, artifacts.

The server checks the datasets, builds the global policy exactly as clients do (same base,
same seed) on its evaluation dataset, and runs Flower's round loop with the run's server
optimiser (a Flower strategy, zk0.federation.server_optimisers) inside ``ValidatingStrategy``: only the
trainable arrays travel, updates are averaged by samples trained and stepped by the optimiser
(whose state a resumed run gets back from its checkpoint), Flower's
``evaluate_fn`` (``ServerEvaluation``) evaluates the global model every ``eval-frequency``
rounds, and ``RoundArtifacts`` (zk0.federation.round_artifacts) writes what each round leaves.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from flwr.app import ArrayRecord, ConfigRecord, Context, MetricRecord
from flwr.serverapp import Grid, ServerApp
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from loguru import logger

from zk0 import app_fingerprint
from zk0.artifacts.disk import bytes_needed, check_room, checkpoint_bytes, full_disk_in_one_sentence
from zk0.artifacts.logs import add_file_sink, prints_to_log, say, setup_logging
from zk0.artifacts.report import REPORT_FILE
from zk0.artifacts.resume import ResumePoint, find_resume_point
from zk0.artifacts.run_folder import History, checkpoints, new_run_dir, write_json
from zk0.artifacts.tracking import Tracker
from zk0.common.errors import Zk0Error
from zk0.config import ConfigError, RunConfig, from_run_config
from zk0.data.loaders import DataError, DatasetSplit, eval_loader, open_evaluation
from zk0.data.registry import Registry, load_registry
from zk0.deployment.grid import PromptGrid
from zk0.federation import stopping
from zk0.federation.aggregation import ValidatingStrategy
from zk0.federation.privacy import OwnerLevelDP, PrivacyBudgetSpent
from zk0.federation.robust import Trusted, make_rule
from zk0.federation.round_artifacts import RoundArtifacts
from zk0.federation.server_optimisers import make_strategy, restore_state
from zk0.federation.trusted import TrustedDirection
from zk0.federation.updates import array_signature
from zk0.federation.waiting import OwnersGone, OwnersWatch
from zk0.federation.wire import SHAPE
from zk0.internals import is_simulation, shorten_object_pull_backoff
from zk0.learning.policy import (
    PolicyBundle,
    backbone_fingerprint,
    build_policy,
    config_features,
    get_trainable,
    set_trainable,
)
from zk0.learning.policy_types import name_of
from zk0.learning.preflight import SIZED, check_federation
from zk0.learning.training import evaluate

app = ServerApp()


class ServerEvaluation:
    """Flower's ``evaluate_fn``: the global model's policy loss and action MSE on the server's own
    held-out dataset, in the rounds the run evaluates (round 0 is the starting model); with
    ``sim-eval-episodes``, also its success rate in closed loop in the simulator, and a video."""

    def __init__(self, run: RunConfig, bundle: PolicyBundle, split: DatasetSplit, run_dir: Path):
        self.run, self.bundle, self.split = run, bundle, split
        self.loader = eval_loader(split.evaluation, run)
        self.videos = run_dir / "server" / "videos"
        self.closed_loop = None
        if run.sim_eval_episodes:
            from zk0.learning.closed_loop import ClosedLoop  # MuJoCo and a renderer: only when asked for

            height, width, _ = split.meta.features["observation.images.front"]["shape"]
            self.closed_loop = ClosedLoop(
                split.entry.name, run.sim_eval_episodes, run.seed, height, width, run.sim_episode_length
            )

    def __call__(self, server_round: int, arrays: ArrayRecord) -> MetricRecord | None:
        if server_round and not self.run.evaluates_in(server_round):
            return None
        run = self.run
        with self.bundle.lock:  # models/best may still be being written from this policy
            set_trainable(self.bundle, arrays)
            metrics = evaluate(self.bundle, self.split, self.loader, run.eval_batches, run.seed, run.max_skip_fraction)
            if self.closed_loop:
                stopping.check(server_round)
                self.videos.mkdir(parents=True, exist_ok=True)
                metrics |= self.closed_loop(self.bundle, self.videos / f"round_{server_round}.mp4")
        logger.info("Round {} server evaluation on {}: {}", server_round, self.split.entry.name, metrics)
        return MetricRecord(metrics)

    def close(self) -> None:
        if self.closed_loop:
            self.closed_loop.close()


def record_run_config(run: RunConfig, run_dir: Path, resumed: ResumePoint | None) -> None:
    """Keep the run config with the run; a resumed run says which settings changed."""
    path = run_dir / "server" / "run_config.json"
    if resumed:
        say("Resuming {} after round {} (checkpoint {})", run_dir, resumed.round, resumed.checkpoint.name)
        before = json.loads(path.read_text()) if path.is_file() else {}
        changed = {k: (before.get(k), v) for k, v in run.to_flat().items() if k != "resume-from" and before.get(k) != v}
        if changed:
            logger.warning("The resumed run differs from the original in {}", changed)
    else:
        say("Writing to {}", run_dir)
    write_json(path, run.to_flat())


def describe_run(run: RunConfig, registry: Registry, bundle: PolicyBundle) -> None:
    """The console's header: who takes part, the model and where it trains, how long the run is."""
    clients = ", ".join(f"{i} {e.name}" for i, e in enumerate(registry.clients))
    say("{} clients: {}; the server evaluates on {}", len(registry.clients), clients, run.server_eval_dataset)
    adapters = "" if run.peft == "none" else f" with {run.peft} adapters"
    say(
        "Model: {} {}{} ({:,} trainable parameters in {} tensors) on {}; server optimiser {}",
        run.model,
        name_of(bundle.policy.config),
        adapters,
        sum(p.numel() for p in bundle.policy.parameters() if p.requires_grad),
        len(bundle.trainable_names),
        bundle.device,
        run.server_optimiser,
    )
    say(
        "{} round{} x {} local steps (batch {}), evaluated every {}",
        run.num_server_rounds,
        "s" * (run.num_server_rounds != 1),
        run.local_steps,
        run.batch_size,
        "round" if run.eval_frequency == 1 else f"{run.eval_frequency} rounds",
    )


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


def trusted_direction(run: RunConfig, registry: Registry) -> Trusted | None:
    """``aggregation = "monna"``: the server's own update on the registry's public sets each round,
    refused in one sentence before round 1 when the registry has none."""
    if run.aggregation != "monna":
        return None
    with refusals_in_one_sentence():
        if not registry.public:
            raise ConfigError(
                "Run-config key 'aggregation' = 'monna' scores the owners' updates against the server's own on public "
                f"data, and registry {run.registry or 'pyproject.toml'!r} has none; expected entries with role = "
                '"public" (or public = <count> in [tool.zk0.owners]), or another aggregation.'
            )
        return TrustedDirection(run, registry).update


def owner_privacy(run: RunConfig, owners: int, resumed: ResumePoint | None) -> OwnerLevelDP | None:
    """Owner-level DP for ``dp = "owner"`` (``owners``: the registry's clients), continuing a resumed
    run's accounting from its checkpoint round's record; None otherwise."""
    if run.dp != "owner":
        return None
    state = resumed.rounds.get(resumed.round, {}).get("privacy", {}).get("accountant") if resumed else None
    privacy = OwnerLevelDP(run, owners, state)
    say(
        "Owner-level differential privacy: each update clipped to {:g}, noise multiplier {:.3g}; epsilon so far {:.3g} "
        "of dp-epsilon-budget={:g} at delta {:g} (Flower's RDP accountant)",
        run.dp_clip,
        privacy.noise_multiplier,
        privacy.spent()["epsilon"],
        run.dp_epsilon_budget,
        run.dp_delta,
    )
    return privacy


@contextmanager
def refusals_in_one_sentence() -> Iterator[None]:
    """A refusal of the user's input (a ``Zk0Error``) logged as its one sentence, before Flower's
    own report of the failure, which shows only that the ServerApp raised."""
    try:
        yield
    except Zk0Error as err:
        logger.error("zk0: {}", err)
        raise


@app.main()
def main(grid: Grid, context: Context) -> None:
    """Validate the config and every local dataset, build the global model, run the federation,
    write artifacts every round."""
    setup_logging("server")
    shorten_object_pull_backoff()  # the replies' arrays, pulled from the SuperLink
    with refusals_in_one_sentence():
        run = from_run_config(dict(context.run_config))
        registry = load_registry(run.registry)
        resumed = find_resume_point(run.resume_from) if run.resume_from else None
        meta = preflight(run, registry, simulation=is_simulation(grid))
        run_dir = resumed.run_dir if resumed else new_run_dir(run.output_dir)
    entry = registry.get(run.server_eval_dataset)
    add_file_sink(run_dir / "server" / "server.log", "server")
    record_run_config(run, run_dir, resumed)
    done = resumed.round if resumed else 0
    if done >= run.num_server_rounds:
        logger.info(
            "{} already has round {} of num-server-rounds={}; nothing to do.", run_dir, done, run.num_server_rounds
        )
        return

    with refusals_in_one_sentence(), prints_to_log("lerobot"):  # e.g. lora-targets that match no module
        bundle = build_policy(run, meta, entry, registry.model_cameras())
        check_room(run_dir, bytes_needed(run, done + 1, checkpoint_bytes(bundle)))
    initial = resumed.trainable(bundle) if resumed else get_trainable(bundle)
    describe_run(run, registry, bundle)
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
    client_stats = dict(resumed.client_stats) if resumed else {}
    artifacts = RoundArtifacts(
        run, registry, bundle, entry, history, tracker, client_stats, done + 1, resumed.best if resumed else None
    )
    optimiser = make_strategy(
        run.server_optimiser,
        run.server_lr,
        run.server_momentum,
        fraction_train=run.fraction_train,
        fraction_evaluate=run.fraction_evaluate,
        min_train_nodes=run.min_train_clients,
        min_evaluate_nodes=1,
        min_available_nodes=run.min_train_clients,
    )
    if resumed:
        restore_state(optimiser, resumed.server_state, list(initial), resumed.server_optimiser)
    with refusals_in_one_sentence():
        privacy = owner_privacy(run, len(registry.clients), resumed)
    strategy = ValidatingStrategy(
        optimiser,
        expected=array_signature(initial),
        evaluates_in=run.evaluates_in,
        checkpoints_in=run.checkpoints_in,
        observer=artifacts,
        last_round=run.num_server_rounds,
        round_offset=done,
        wire_dtype=run.wire_dtype,
        proximal_mu=run.proximal_mu,
        update_clip=run.update_clip,
        averaging=run.averaging,
        privacy=privacy,
        rule=make_rule(run, optimiser.weighted_by_key, trusted_direction(run, registry)),
        owners=OwnersWatch(run.min_train_clients, run.wait_for_owners_s, simulated=is_simulation(grid)),
    )
    # The run's folder name (clients keep their logs under a folder of that name on their own
    # machine, never at a path of the server's) and what both ends must share.
    shared = {
        "backbone-fingerprint": fingerprint,
        "app-fingerprint": app_fingerprint(),
        "run-name": run_dir.name,
        **{SHAPE + key: list(ft.shape) for key, ft in config_features(bundle.policy.config).items() if key in SIZED},
    }
    evaluation = ServerEvaluation(run, bundle, split, run_dir)
    resume = f"free some space there and resume the run from its last complete checkpoint: resume-from='{run_dir}'."
    try:
        with stopping.watching(), full_disk_in_one_sentence(run_dir, resume):
            strategy.start(
                grid=PromptGrid(grid, train_deadline_s=run.round_deadline_s),
                initial_arrays=initial,
                num_rounds=run.num_server_rounds - done,
                train_config=ConfigRecord(dict(shared)),
                evaluate_config=ConfigRecord(dict(shared)),
                evaluate_fn=evaluation,
                timeout=run.phase_timeout,
            )
    except stopping.RunStopped:
        return  # Flower is ending the process, and it was said: no traceback, no failure
    except PrivacyBudgetSpent as err:
        artifacts.finish_writes()  # models/best may still be being written
        say("{}", err)  # the run did what its privacy budget allows: an end, not a failure
    except OwnersGone as err:  # the operator's call to make, not a failure: the checkpoint resumes it
        artifacts.finish_writes()
        resume = f": ./train.sh --resume {run_dir} (or resume-from='{run_dir}') continues it once they are back"
        say("{}{}.", err, resume if checkpoints(run_dir) else "")
    except Zk0Error as err:
        logger.error("zk0: {}", err)
        raise
    finally:
        evaluation.close()
        tracker.finish()
    say("Done in {:.0f} s: {}.", artifacts.elapsed(), artifacts.summary())
    say("Report: {}", run_dir / REPORT_FILE)
