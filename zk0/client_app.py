"""zk0 ClientApp: one robot owner's dataset, local FedProx steps, held-out evaluation.

Building SmolVLA and opening videos is the expensive part, so a client keeps its policy,
processors, dataset, data iterator and optimizer in memory for the whole run (one
``ClientSession`` per run and node in this process) and only loads the global weights
each round. Where a process serves only one message (a SuperNode's ``flwr-clientapp``),
the optimizer state and the data-order position travel in Flower's ``Context.state``
instead, so training continues exactly where the previous round stopped. Replies carry the trainable arrays, one MetricRecord with the same keys on
every client, and the dataset statistics the server merges into its checkpoints.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from flwr.app import ConfigRecord, Context, Message, MetricRecord, RecordDict
from flwr.clientapp import ClientApp
from loguru import logger
from torch.utils.data import DataLoader

from zk0.artifacts import client_dir
from zk0.config import RunConfig, from_run_config
from zk0.data import DatasetSplit, eval_loader, open_metadata, open_split, train_loader
from zk0.logs import add_file_sink, setup_logging
from zk0.policy import PolicyBundle, PolicyError, backbone_fingerprint, build_policy, set_trainable, trainable_tensors
from zk0.registry import Registry, RegistryError, load_registry
from zk0.stats import stats_to_record
from zk0.training import LocalTrainer, evaluate
from zk0.wire import decode, encode

app = ClientApp()


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


_SESSIONS: dict[tuple[int, int], ClientSession] = {}
# What must outlive the ClientApp process: a SuperNode runs each message in a fresh process and
# keeps the node's Context.state for the run (see docs/deployment.md).
OPTIMIZER, PROGRESS = "zk0-optimizer", "zk0-progress"


def dataset_index(registry: Registry, context: Context) -> int:
    """The client's registry index: ``dataset`` in the node config, else the simulation partition id."""
    if "dataset" in context.node_config:
        entry = registry.get(str(context.node_config["dataset"]))
        if entry not in registry.clients:
            raise RegistryError(f"Dataset {entry.name!r} has role {entry.role!r}; a SuperNode needs a client dataset.")
        return registry.clients.index(entry)
    partition = int(context.node_config.get("partition-id", 0))
    registry.for_partition(partition)
    return partition


def session_for(context: Context, config: ConfigRecord) -> ClientSession:
    """This run's session for this node, built on first use; sessions of older runs are dropped."""
    key = (context.run_id, context.node_id)
    if key in _SESSIONS:
        return _SESSIONS[key]
    for stale in [k for k in _SESSIONS if k[0] != context.run_id]:
        del _SESSIONS[stale]
    setup_logging("client")
    run = from_run_config(dict(context.run_config))
    registry = load_registry(run.registry)
    index = dataset_index(registry, context)
    party = f"client {index}"
    add_file_sink(client_dir(Path(str(config["run-dir"])), index) / "client.log", party)
    with logger.contextualize(party=party):
        entry = registry.clients[index]
        meta = open_metadata(entry)
        bundle = build_policy(run, meta, entry, registry.model_cameras())
        split = open_split(entry, meta, bundle.policy.config, run)
        trainer = LocalTrainer(bundle, split, train_loader(split.train, run, bundle.device), run)
        fingerprint = backbone_fingerprint(bundle)
        logger.info(
            "Opened {} ({} training, {} held-out episodes) and built SmolVLA ({} trainable tensors) on {}",
            entry.name,
            len(split.train.episodes),
            len(split.evaluation.episodes),
            len(bundle.trainable_names),
            bundle.device,
        )
    session = ClientSession(run, index, bundle, split, trainer, eval_loader(split.evaluation, run), fingerprint, party)
    _SESSIONS[key] = session
    return session


def _catch_up(session: ClientSession, context: Context) -> None:
    """Continue from the node's latest training state when another process trained it since.

    A SuperNode runs each message in a new process, and Ray may give a simulated node to another
    actor for a round; either way the node's ``Context.state`` holds where training stopped.
    """
    if PROGRESS in context.state:
        seen = int(context.state[PROGRESS]["batches-seen"])
        if seen != session.trainer.batches_seen:
            session.trainer.restore(seen, context.state[OPTIMIZER])


def _load_global(session: ClientSession, msg: Message) -> None:
    """Check the server's backbone fingerprint and load the global trainable weights."""
    config = msg.content["config"]
    if config["backbone-fingerprint"] != session.fingerprint:
        raise PolicyError(
            f"Client {session.index} ({session.split.entry.name}) has backbone fingerprint {session.fingerprint}, "
            f"the server has {config['backbone-fingerprint']}; every party must start from the same base model and seed."
        )
    set_trainable(session.bundle, decode(msg.content["arrays"], session.run.wire_dtype))


@app.train()
def train(msg: Message, context: Context) -> Message:
    """Load the global trainable weights, take ``local-steps`` FedProx steps, send the new weights back."""
    session = session_for(context, msg.content["config"])
    with logger.contextualize(party=session.party):
        _load_global(session, msg)
        _catch_up(session, context)
        server_round = int(msg.content["config"]["server-round"])
        run = session.run
        metrics = session.trainer.fit(
            run.local_steps, float(msg.content["config"]["proximal-mu"]), (server_round - 1) * run.local_steps
        )
        logger.info("Round {} train on {}: {}", server_round, session.split.entry.name, metrics)
        context.state[OPTIMIZER] = session.trainer.optimizer_record()
        context.state[PROGRESS] = ConfigRecord({"batches-seen": session.trainer.batches_seen})
        update = encode(trainable_tensors(session.bundle), run.wire_dtype)
        content = RecordDict(
            {
                "arrays": update,
                "metrics": MetricRecord(
                    {**metrics, "update-bytes": update.count_bytes(), "dataset-index": session.index}
                ),
                "stats": stats_to_record(session.bundle.stats),
            }
        )
    return Message(content=content, reply_to=msg)


@app.evaluate()
def evaluate_(msg: Message, context: Context) -> Message:
    """Policy loss and action MSE of the global model on this client's held-out episodes."""
    session = session_for(context, msg.content["config"])
    with logger.contextualize(party=session.party):
        _load_global(session, msg)
        run = session.run
        metrics = evaluate(session.bundle, session.split, session.eval_batches, run.eval_batches, run.seed)
        logger.info(
            "Round {} evaluate on {}: {}", msg.content["config"]["server-round"], session.split.entry.name, metrics
        )
        content = RecordDict({"metrics": MetricRecord({**metrics, "dataset-index": session.index})})
    return Message(content=content, reply_to=msg)
