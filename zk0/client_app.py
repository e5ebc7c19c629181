"""zk0 ClientApp: one robot owner's dataset, local FedProx steps, held-out evaluation.

The handlers are thin. In simulation, and on a SuperNode without the warm worker, the client
is built and kept in this process (``zk0.federation.client``). On a SuperNode started by ``zk0 supernode``
each message runs in a fresh process, so it is handed to the run's warm worker
(``zk0.deployment.worker``), which keeps the client built for the whole run; this module then imports no
torch or lerobot at all, which is what keeps a message cheap.
"""

from __future__ import annotations

import time

from flwr.app import Context, Error, Message, RecordDict
from flwr.clientapp import ClientApp
from loguru import logger

from zk0.common.errors import REFUSED, Zk0Error
from zk0.deployment import worker

app = ClientApp()


@app.train()
def train(msg: Message, context: Context) -> Message:
    """Load the global trainable weights, take ``local-steps`` FedProx steps, send the new weights back."""
    return _reply("train", msg, context)


@app.evaluate()
def evaluate(msg: Message, context: Context) -> Message:
    """Policy loss and action MSE of the global model on this client's held-out episodes."""
    return _reply("evaluate", msg, context)


def _reply(kind: str, msg: Message, context: Context) -> Message:
    """The handler's reply, or for the owner's own mistake (a bad dataset, say) an error reply whose
    reason is zk0's one sentence: the server prints it, and no traceback buries it."""
    try:
        return Message(content=_handle(kind, msg, context), reply_to=msg)
    except Zk0Error as err:
        logger.error("zk0: {}", err)
        return Message(Error(code=REFUSED, reason=str(err)), reply_to=msg)


def _handle(kind: str, msg: Message, context: Context) -> RecordDict:
    if worker.enabled(context.node_config):
        started, age = time.perf_counter(), _process_age()
        try:
            reply, worker_s = worker.call(kind, msg.content, context, arrived=time.time() - age)
        except worker.WorkerUnavailable as err:
            logger.warning("{}; handling this message in the ClientApp process instead.", err)
        else:
            metrics = next(iter(reply.metric_records.values()))
            metrics.update({"startup-s": age, "worker-s": worker_s, "handler-s": time.perf_counter() - started})
            return reply
    from zk0.federation import client  # torch, lerobot: only where this process does the work itself

    reply = client.handle(kind, msg.content, context)
    next(iter(reply.metric_records.values()))["worker-s"] = 0.0
    return reply


def _process_age() -> float:
    """Seconds since this process started: what Flower's per-message process costs before the handler."""
    import psutil

    return time.time() - psutil.Process().create_time()
