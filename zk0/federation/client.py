"""One robot owner's client: dataset, SmolVLA and local trainer, built once and reused every round.

``build_client`` is the one way a client is built (the ClientApp, the SuperNode's warm worker
and the benchmarks call it). ``handle`` answers one train or evaluate message with it: it
checks the server's fingerprints, loads the global weights, trains or evaluates, and says in
the reply's metrics where the message's time went (process start, model build, state restore,
steps, evaluation), so the deployment benchmark can split a round without guessing.

A process keeps one ``ClientSession`` per run and node (a Ray actor in simulation, the warm
worker on a SuperNode). Where a process serves only one message (a SuperNode's
``flwr-clientapp`` without the worker), what training needs to continue travels in Flower's
``Context.state``: the data-order position always, the optimizer state when asked.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import psutil
import torch
from flwr.app import ConfigRecord, Context, MetricRecord, RecordDict
from loguru import logger
from torch.utils.data import DataLoader

from zk0 import app_fingerprint
from zk0.artifacts.disk import full_disk_in_one_sentence
from zk0.artifacts.logs import add_file_sink, prints_to_log, setup_logging
from zk0.common import machine
from zk0.common.errors import Zk0Error
from zk0.config import ConfigError, RunConfig, from_run_config
from zk0.data.loaders import DatasetSplit, eval_loader, open_split, train_loader
from zk0.data.registry import DatasetEntry, Registry, load_registry
from zk0.federation.growth import grown
from zk0.federation.personal import Personaliser, build_personaliser
from zk0.federation.stats import stats_to_record
from zk0.federation.wire import CLIENT, EVALUATE_ROUND, EVALUATION, KEEP_STATE, SHAPE, decode, encode
from zk0.learning import client_state
from zk0.learning.memory import room_for_another
from zk0.learning.policy import (
    PolicyBundle,
    PolicyError,
    backbone_fingerprint,
    build_policy,
    set_trainable,
    trainable_tensors,
)
from zk0.learning.policy_types import name_of
from zk0.learning.preflight import check_dataset, model_inputs
from zk0.learning.training import LocalTrainer, evaluate

# What must outlive a one-message process, in the node's Context.state.
OPTIMIZER, PROGRESS = "zk0-optimizer", "zk0-progress"
HELD_OUT = "zk0-held-out"  # Context.state: the episodes this client holds out, fixed for the run
# Timing keys every reply carries (the same keys on every client, as Flower's averaging needs).
TIMINGS = ("startup-s", "build-s", "restore-s", "handler-s")


@dataclass
class ClientSession:
    """Everything one client keeps between rounds of one run."""

    run: RunConfig
    index: int
    bundle: PolicyBundle
    split: DatasetSplit
    trainer: LocalTrainer
    eval_batches: DataLoader
    fingerprint: str
    party: str
    personal: Personaliser | None = None  # with personal-steps: built at the first evaluation
    said_of_growth: set[str] = field(default_factory=set)  # why new episodes were refused, said once each


def client_index(registry: Registry, node_config: dict) -> int:
    """The client's registry index: ``dataset`` in the node config, else the simulation partition id."""
    if "dataset" in node_config:
        return registry.clients.index(registry.get_client(str(node_config["dataset"])))
    partition = int(node_config.get("partition-id", 0))
    registry.for_partition(partition)
    return partition


def trainer_kind(run: RunConfig) -> type[LocalTrainer]:
    """The trainer ``run`` asks for: DP-SGD of each demonstration with ``dp = "record"``, else the
    plain one. Opacus is imported only then: it is 0.8 s of every client process's start."""
    if run.dp != "record":
        return LocalTrainer
    from zk0.learning.record_privacy import PrivateTrainer

    return PrivateTrainer


def build_client(
    run: RunConfig,
    entry: DatasetEntry,
    model_cameras: list[str],
    index: int = 0,
    shapes: dict | None = None,
    held_out: list[int] | None = None,
) -> ClientSession:
    """Check and open ``entry`` (client ``index``) and build its SmolVLA, split, loaders and trainer.

    ``shapes`` are the global model's state/action sizes, as the server sends them; ``held_out``
    the episodes this client held out earlier in the run (its dataset may have grown since).
    """
    party = f"client {index}"
    with logger.contextualize(party=party):
        meta = check_dataset(entry, model_inputs(run, model_cameras, shapes), run.eval_episodes)
        bundle = build_policy(run, meta, entry, model_cameras)
        split = open_split(entry, meta, bundle.policy.config, run, held_out)
        trainer = trainer_kind(run)(bundle, split, train_loader(split.train, run, bundle.device), run)
        fingerprint = backbone_fingerprint(bundle)
        logger.info(
            "Opened {} ({} training, {} held-out episodes) and built {} ({} trainable tensors) on {}; app {}",
            entry.name,
            len(split.train.episodes),
            len(split.evaluation.episodes),
            name_of(bundle.policy.config),
            len(bundle.trainable_names),
            bundle.device,
            app_fingerprint(),
        )
    return ClientSession(run, index, bundle, split, trainer, eval_loader(split.evaluation, run), fingerprint, party)


def client_log(node_config: dict, run: RunConfig, run_name: str, index: int) -> Path:
    """Where this client writes its log: under its own output folder, never at a path the server names.

    A SuperNode names its folder (``zk0 supernode --output-dir``, node config ``output-dir``); a
    simulated client shares the server's machine and uses the run's ``output-dir``, so its log
    lands in the run folder next to the server's.
    """
    if not re.fullmatch(r"[\w.-]+", run_name) or run_name in {".", ".."}:
        raise ConfigError(f"The server named the run {run_name!r}; expected a plain folder name.")
    root = Path(str(node_config.get("output-dir", run.output_dir))).expanduser()
    return root / run_name / "clients" / f"client_{index}" / "client.log"


_SESSIONS: dict[tuple[int, int], ClientSession] = {}  # least recently used first
# A process keeps the sessions (SmolVLA, optimizer, dataset) of at most this many nodes. A Ray actor
# of a simulation runs whichever nodes it is given: with 64 owners sampled a few a round it would
# otherwise keep every owner it ever met (a full-size SmolVLA each). Four covers the quick
# federation's owners, so a simulation of four rebuilds nothing; an owner met again after being
# dropped is rebuilt and continues from its node's Context.state (zk0.federation.client._catch_up).
# Where the memory available would not hold one more (a full-size SmolVLA on a CPU machine), a
# process drops those it keeps before it builds another (zk0.learning.memory.room_for_another).
SESSIONS_KEPT = 4
_FRESH_PROCESS = True  # the first message a process handles also paid for the process's start


def session_for(context: Context, config: ConfigRecord) -> tuple[ClientSession, float]:
    """This run's session for this node, built on first use (and the seconds that took)."""
    key = (context.run_id, context.node_id)
    if key in _SESSIONS:
        _SESSIONS[key] = _SESSIONS.pop(key)  # now the most recently used
        return _SESSIONS[key], 0.0
    run = from_run_config(dict(context.run_config))
    release_sessions(keep_run=context.run_id, keep=SESSIONS_KEPT - 1 if room_for_another(run) else 0)
    started = time.perf_counter()
    setup_logging("client")
    registry = load_registry(run.registry)
    index = client_index(registry, dict(context.node_config))
    entry = registry.clients[index]
    add_file_sink(client_log(dict(context.node_config), run, str(config["run-name"]), index), f"client {index}")
    held = context.state.config_records.get(HELD_OUT)
    with _named(index, entry.name), prints_to_log("lerobot"):
        session = build_client(
            run, entry, registry.model_cameras(), index, model_shapes(config), list(held["episodes"]) if held else None
        )
    context.state[HELD_OUT] = ConfigRecord({"episodes": list(session.split.evaluation.episodes)})
    _SESSIONS[key] = session
    return session, time.perf_counter() - started


def client_label(index: int, dataset: str) -> str:
    """How the server's log names a client: its registry index and dataset, never a node id."""
    return f"Client {index} ({dataset})"


@contextmanager
def _named(index: int, dataset: str) -> Iterator[None]:
    """Prefix a user error's sentence with the client it happened on: the server reads it without
    knowing which node is which client."""
    label = client_label(index, dataset)
    try:
        yield
    except Zk0Error as err:
        if str(err).startswith(label):
            raise
        raise type(err)(f"{label}: {err}") from None


def model_shapes(config: ConfigRecord) -> dict[str, tuple[int, ...]]:
    """The global model's state/action sizes from the server's config (``shape:<feature>`` keys)."""
    return {key.removeprefix(SHAPE): tuple(value) for key, value in config.items() if key.startswith(SHAPE)}


def release_sessions(keep_run: int | None = None, keep: int = 0) -> None:
    """Drop the sessions of other runs, and of run ``keep_run`` all but its ``keep`` most recently
    used (their policy, optimizer and GPU memory)."""
    ours = [k for k in _SESSIONS if k[0] == keep_run]
    for stale in [k for k in _SESSIONS if k[0] != keep_run] + ours[: max(0, len(ours) - keep)]:
        session = _SESSIONS.pop(stale)
        if session.personal:
            session.personal.close()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()


def _check_server(session: ClientSession, config: ConfigRecord) -> None:
    """Refuse a server whose app code or frozen backbone differs from this client's (one sentence each)."""
    name = client_label(session.index, session.split.entry.name)
    if str(config["app-fingerprint"]) != app_fingerprint():
        raise PolicyError(
            f"{name} runs zk0 {app_fingerprint()}, the server runs zk0 {config['app-fingerprint']}; "
            "every party must run the submitted app's code."
        )
    if config["backbone-fingerprint"] != session.fingerprint:
        raise PolicyError(
            f"{name} has backbone fingerprint {session.fingerprint}, the server has "
            f"{config['backbone-fingerprint']}; every party must start from the same base model and seed."
        )


def _catch_up(session: ClientSession, context: Context, config: ConfigRecord) -> float:
    """Continue from the node's latest training state when another process trained it since.

    A SuperNode may run a message in a new process, and Ray may give a simulated node to another
    actor for a round; either way the node's ``Context.state`` holds where training stopped. A
    resumed run's first round continues from the state this client kept on disk at the
    checkpoint the server resumed from, and a SuperNode restarted mid-run (its ``Context.state``
    gone with its process) from the last one it kept (zk0.learning.client_state). It trains from
    the global model of the round it is sent, never an older one. Returns the seconds it took.
    """
    started = time.perf_counter()
    if PROGRESS in context.state:
        seen = int(context.state[PROGRESS]["batches-seen"])
        if seen == session.trainer.batches_seen:
            return 0.0
        optimizer = context.state.array_records.get(OPTIMIZER)
        if optimizer is None:
            logger.warning("Continuing at batch {} without the optimizer's moments (they were not kept).", seen)
        session.trainer.restore(seen, optimizer)
    elif session.trainer.batches_seen == 0:
        previous = int(config["server-round"]) - 1
        if (state := client_state.kept(state_folder(session, context, config), previous)) is None:
            return 0.0
        kept_round, seen, optimizer = state
        logger.info("Continuing at batch {} with the optimizer state this client kept after round {}.", seen, kept_round)
        session.trainer.restore(seen, optimizer)
    return time.perf_counter() - started


def take_new_episodes(session: ClientSession) -> None:
    """Train on the episodes the owner recorded since the client opened its dataset
    (zk0.federation.growth): the trainer, and the personal model's fine-tuner, go on from the
    grown training set."""
    split = grown(session.split, session.run, session.bundle.policy.config, session.said_of_growth)
    if split is None:
        return
    session.split = split
    session.trainer.train_on(split, train_loader(split.train, session.run, session.bundle.device))
    if session.personal:
        tuner = session.personal.trainer
        tuner.train_on(split, train_loader(split.train, tuner.run, session.bundle.device))


def state_folder(session: ClientSession, context: Context, config: ConfigRecord) -> Path:
    """Where this client keeps its training state for the run: next to its log."""
    log = client_log(dict(context.node_config), session.run, str(config["run-name"]), session.index)
    return log.parent / "trainer_state"


def _train(
    session: ClientSession, content: RecordDict, context: Context, keep_optimizer: bool, began: float
) -> RecordDict:
    """Evaluate the received model first when the server asks (it is the previous round's), then train."""
    config = content["config"]
    server_round = int(config["server-round"])
    run = session.run
    evaluation = _evaluate_before_training(session, content, context) if int(config.get(EVALUATE_ROUND, 0)) else None
    first_step = (server_round - 1) * run.local_steps  # the round's place on the schedule, whatever it takes
    budget = training_budget(run.local_time_s, time.perf_counter() - began)
    metrics = session.trainer.fit(run.local_steps, float(config["proximal-mu"]), first_step, budget)
    logger.info("Round {} train on {}: {}", server_round, session.split.entry.name, metrics)
    if "dp-epsilon-spent" in config:
        logger.info(
            "Owner-level privacy: the models released before round {} have spent epsilon {:.3f} at delta {:g} of "
            "dp-epsilon-budget={:g} (the server's accountant)",
            server_round,
            float(config["dp-epsilon-spent"]),
            run.dp_delta,
            run.dp_epsilon_budget,
        )
    if keep_optimizer:
        context.state[OPTIMIZER] = session.trainer.optimizer_record()
    if config.get(KEEP_STATE):
        client_state.keep(state_folder(session, context, config), server_round, session.trainer)
    context.state[PROGRESS] = ConfigRecord({"batches-seen": session.trainer.batches_seen})
    update = encode(trainable_tensors(session.bundle), run.wire_dtype)
    reply = RecordDict(
        {
            "arrays": update,
            "metrics": MetricRecord(
                {
                    **metrics,
                    "update-bytes": update.count_bytes(),
                    "evaluate-s": float(evaluation.get("eval-s", 0.0)) if evaluation else 0.0,
                    "budget-s": budget,
                }
            ),
            CLIENT: identity(session),
        }
    )
    if run.dp == "off":  # under DP the statistics (each feature's min and max among them) stay home
        reply["stats"] = stats_to_record(session.bundle.stats)
    if evaluation:
        reply[EVALUATION] = ConfigRecord(dict(evaluation))  # one MetricRecord per reply, as Flower requires
    return reply


def training_budget(local_time_s: float, spent_s: float) -> float:
    """The seconds left to train of a round's ``local-time-s`` (0 = no budget) once ``spent_s`` went
    on the message's other work: the evaluation it carries and catching up. The budget bounds the
    client's whole answer, so a round lasts about the budget however long evaluating takes on a
    slow machine; training still takes at least one step (``LocalTrainer.fit``)."""
    if not local_time_s:
        return 0.0
    return max(local_time_s - spent_s, 1e-9)


def _evaluate_before_training(session: ClientSession, content: RecordDict, context: Context) -> dict:
    """The received model's evaluation, or why it failed: a failed evaluation (unreadable held-out
    frames, say) is reported to the server and does not cost the round's training."""
    try:
        return dict(_evaluate(session, content, context)["metrics"])
    except Zk0Error as err:
        reason = f"{client_label(session.index, session.split.entry.name)}: {err}"
        logger.error("zk0: {}", reason)
        return {"error": reason}


def _evaluate(session: ClientSession, content: RecordDict, context: Context) -> RecordDict:
    """The received global model on this client's held-out episodes; with ``personal-steps``, its
    personal model beside it (fine-tuned from it, kept on this machine: zk0.federation.personal)."""
    run = session.run
    metrics = evaluate(
        session.bundle, session.split, session.eval_batches, run.eval_batches, run.seed, run.max_skip_fraction
    )
    evaluated = int(content["config"].get(EVALUATE_ROUND, content["config"]["server-round"]))
    if run.personal_steps and run.personalises_in(evaluated):
        if session.personal is None:
            session.personal = build_personaliser(run, session.bundle, session.split, session.eval_batches)
        metrics |= session.personal(evaluated, state_folder(session, context, content["config"]).parent, metrics)
    logger.info("Round {} evaluate on {}: {}", evaluated, session.split.entry.name, metrics)
    return RecordDict({"metrics": MetricRecord(metrics), CLIENT: identity(session)})


def identity(session: ClientSession) -> ConfigRecord:
    """Who replies: the client's registry index and dataset (never averaged, unlike metrics)."""
    return ConfigRecord({"index": session.index, "dataset": session.split.entry.name})


def share_this_machine() -> None:
    """On a SuperNode, PyTorch's threads for this message: the SuperNode's share of the machine
    (``--cpus``, or the CPUs divided among the SuperNodes running now: zk0.common.machine)."""
    cpus = machine.cpus_now()
    if cpus is not None and cpus != torch.get_num_threads():
        torch.set_num_threads(cpus)


def handle(
    kind: str, content: RecordDict, context: Context, keep_optimizer: bool = True, arrived: float | None = None
) -> RecordDict:
    """Answer one ``train`` or ``evaluate`` message for this node; ``context.state`` is updated in place.

    ``keep_optimizer`` puts the optimizer's state in ``Context.state`` (a one-message process
    needs it there; a warm worker keeps it in memory instead of copying ~800 MB a round).
    ``arrived`` is when the message reached this machine (Unix time; None: now): a warm worker's
    message first starts a ClientApp process, which on a slow machine takes a second or more of
    the round that ``local-time-s`` bounds.
    """
    global _FRESH_PROCESS
    waited = max(time.time() - arrived, 0.0) if arrived else 0.0
    started = time.perf_counter()
    startup = time.time() - psutil.Process().create_time() if _FRESH_PROCESS else 0.0
    _FRESH_PROCESS = False
    share_this_machine()
    session, build = session_for(context, content["config"])
    began = time.perf_counter() - waited  # local-time-s counts from here: a client is built once, in round 1
    mine = client_log(dict(context.node_config), session.run, str(content["config"]["run-name"]), session.index).parent
    with (
        logger.contextualize(party=session.party),
        _named(session.index, session.split.entry.name),
        full_disk_in_one_sentence(mine, "free some space there; the server goes on with the other clients."),
    ):
        _check_server(session, content["config"])
        set_trainable(session.bundle, decode(content["arrays"], session.run.wire_dtype))
        restore = _catch_up(session, context, content["config"]) if kind == "train" else 0.0
        if kind == "train":
            take_new_episodes(session)
        reply = (
            _train(session, content, context, keep_optimizer, began)
            if kind == "train"
            else _evaluate(session, content, context)
        )
    timings = dict(zip(TIMINGS, (startup, build, restore, time.perf_counter() - started), strict=True))
    next(iter(reply.metric_records.values())).update(timings)
    return reply
