"""FedProx with update validation, evaluation every N rounds, and per-client records.

Flower's ``FedProx`` already does the right thing (FedAvg weighted by ``num-examples``
plus ``proximal-mu`` in the train config). These overrides only add what a federation
of robot owners needs: replies whose arrays are non-finite or do not match the global
model's names/shapes/dtypes are rejected and logged, not averaged; federated evaluation
runs every ``eval-frequency`` rounds; and each client's own metrics and dataset
statistics, and the end of every round, go to an observer (zk0.round_artifacts) that writes them.

Federated evaluation rides on the next round's train message: the model a client receives
for round N+1 is the one round N produced, so it evaluates that first and reports it as round
N's evaluation. On a SuperNode every message costs a process start and two polls of Flower's
(seconds each), so one message per client and round instead of two halves that cost. Only the
last round's model, which no train message follows, gets an evaluate message of its own.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterable
from typing import Protocol

import numpy as np
from flwr.app import ArrayRecord, ConfigRecord, Message, MetricRecord, RecordDict
from flwr.serverapp import Grid
from flwr.serverapp.strategy import FedProx
from loguru import logger

from zk0.errors import REFUSED, Zk0Error
from zk0.wire import CLIENT, EVALUATE_ROUND, EVALUATION, decode, encode


class RoundObserver(Protocol):
    """Who keeps the rounds (zk0.round_artifacts.RoundArtifacts)."""

    def record_clients(
        self,
        phase: str,
        server_round: int,
        replies: list[RecordDict],
        aggregate: MetricRecord | None,
        failures: dict[int, str],
    ) -> None:
        """A phase's replies that counted, their weighted aggregate, failed clients' reasons by index."""

    def round_ended(self, server_round: int, arrays: ArrayRecord, evaluation: MetricRecord | None) -> None:
        """The round is over: ``arrays`` is the global model, ``evaluation`` the server's of it."""


class RunCannotTrain(Zk0Error):
    """The run's first round produced too few updates to train anything."""


def array_signature(arrays: ArrayRecord) -> dict[str, tuple[tuple[int, ...], str]]:
    """Names, shapes and dtypes: what every update must share with the global model."""
    return {name: (tuple(arr.shape), arr.dtype) for name, arr in arrays.items()}


def update_problem(arrays: ArrayRecord, expected: dict[str, tuple[tuple[int, ...], str]]) -> str | None:
    """Why an update cannot be averaged into the global model, or None if it can."""
    signature = array_signature(arrays)
    if set(signature) != set(expected):
        missing, extra = sorted(set(expected) - set(signature)), sorted(set(signature) - set(expected))
        return f"array names differ (missing {missing[:3]}, unexpected {extra[:3]})"
    for name, (shape, dtype) in signature.items():
        if (shape, dtype) != expected[name]:
            return f"{name!r} is {dtype}{list(shape)}, expected {expected[name][1]}{list(expected[name][0])}"
    for name, arr in arrays.items():
        if not np.isfinite(arr.numpy()).all():
            return f"{name!r} holds NaN or infinite values"
    return None


class ValidatingFedProx(FedProx):
    """FedProx that rejects malformed updates and records each client's reply."""

    def __init__(
        self,
        *,
        expected: dict[str, tuple[tuple[int, ...], str]],
        evaluates_in: Callable[[int], bool],
        observer: RoundObserver,
        last_round: int,
        round_offset: int = 0,
        wire_dtype: str = "float32",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.expected = expected
        self.wire_dtype = wire_dtype  # the global model is kept in fp32; messages carry this dtype
        self.evaluates_in = evaluates_in
        self.observer = observer
        self.last_round = last_round  # of the whole run, resumed rounds included
        self.round_offset = round_offset  # rounds a resumed run already has: Flower counts from 1 again
        self.sampled: set[int] = set()  # nodes asked to train this round
        self.node_clients: dict[int, int] = {}  # node id -> client (dataset) index, from their replies

    def start(self, *, evaluate_fn: Callable[[int, ArrayRecord], MetricRecord | None] | None = None, **kwargs):
        """Flower's round loop, run as it is. ``evaluate_fn`` (the server's evaluation, the last step
        of Flower's round) gets the run's round numbers, and after it the observer is told the
        round ended; a resumed run's round 0 is its last checkpoint, evaluated and kept before."""

        def evaluate_and_end_round(flower_round: int, arrays: ArrayRecord) -> MetricRecord | None:
            if flower_round == 0 and self.round_offset:
                return None
            server_round = flower_round + self.round_offset
            evaluation = evaluate_fn(server_round, arrays) if evaluate_fn else None
            self.observer.round_ended(server_round, arrays, evaluation)
            return evaluation

        return super().start(evaluate_fn=evaluate_and_end_round, **kwargs)

    def configure_train(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        server_round += self.round_offset
        wire = encode(arrays.to_torch_state_dict(), self.wire_dtype)
        messages = list(super().configure_train(server_round, wire, config, grid))
        self.sampled = {msg.metadata.dst_node_id for msg in messages}
        previous = server_round - 1
        if previous > self.round_offset and self.evaluates_in(previous):
            self._evaluate_first(messages, previous)
        return messages

    def _evaluate_first(self, messages: list[Message], previous: int) -> None:
        """Ask a ``fraction-evaluate`` sample of the training clients to evaluate round ``previous`` first."""
        count = min(len(messages), max(self.min_evaluate_nodes, int(len(messages) * self.fraction_evaluate)))
        for msg in random.sample(messages, count) if self.fraction_evaluate > 0 else []:
            config = ConfigRecord({**msg.content[self.configrecord_key], EVALUATE_ROUND: previous})
            msg.content = RecordDict({**msg.content, self.configrecord_key: config})

    def _log_missing(self, server_round: int, valid: list[Message]) -> None:
        """Name every sampled node whose update did not arrive (crashed, offline, rejected)."""
        for node in sorted(self.sampled - {msg.metadata.src_node_id for msg in valid}):
            client = self.node_clients.get(node)
            who = f"client {client}" if client is not None else "a client that has not replied yet"
            logger.warning(
                "Round {}: no usable update from node {} ({}); aggregating the others.", server_round, node, who
            )

    def valid_updates(self, server_round: int, replies: Iterable[Message]) -> list[Message]:
        """Replies that may be averaged; every other one is logged with its reason."""
        valid = []
        for msg in replies:
            if msg.has_error():
                self._log_failure(server_round, msg)
                continue
            try:  # averaged in fp32, whatever travelled
                msg.content[self.arrayrecord_key] = ArrayRecord(
                    decode(msg.content[self.arrayrecord_key], self.wire_dtype)
                )
            except Zk0Error as err:
                logger.warning(
                    "Round {}: rejected the update of node {}: {}", server_round, msg.metadata.src_node_id, err
                )
                continue
            problem = update_problem(msg.content[self.arrayrecord_key], self.expected)
            if problem:
                logger.warning(
                    "Round {}: rejected the update of node {}: {}", server_round, msg.metadata.src_node_id, problem
                )
                continue
            valid.append(msg)
            if CLIENT in msg.content:
                self.node_clients[msg.metadata.src_node_id] = int(msg.content[CLIENT]["index"])
        return valid

    @staticmethod
    def _log_failure(server_round: int, msg: Message) -> None:
        """A client's refusal is its own sentence (it names the client and dataset); anything else
        comes from Flower or a crash and is named by node."""
        if msg.error.code == REFUSED:
            logger.error("Round {}: {}", server_round, msg.error.reason)
        else:
            logger.warning("Round {}: node {} failed: {}", server_round, msg.metadata.src_node_id, msg.error.reason)

    def aggregate_train(
        self, server_round: int, replies: Iterable[Message]
    ) -> tuple[ArrayRecord | None, MetricRecord | None]:
        server_round += self.round_offset
        valid = self.valid_updates(server_round, list(replies))
        self._log_missing(server_round, valid)
        self._record_evaluation(server_round - 1, valid)
        if len(valid) < self.min_train_nodes and server_round == self.round_offset + 1:
            raise RunCannotTrain(
                f"Round {server_round} got {len(valid)} usable update(s), fewer than min-train-clients="
                f"{self.min_train_nodes}, so this run cannot train; the clients' reasons are above."
            )
        if len(valid) < self.min_train_nodes:
            logger.warning(
                "Round {}: {} valid updates, fewer than min-train-clients={}; the global model is kept.",
                server_round,
                len(valid),
                self.min_train_nodes,
            )
            self.observer.record_clients("train", server_round, [m.content for m in valid], None, {})
            return None, None
        arrays, metrics = super().aggregate_train(server_round, valid)
        self.observer.record_clients("train", server_round, [m.content for m in valid], metrics, {})
        return arrays, metrics

    def _record_evaluation(self, evaluated_round: int, replies: list[Message]) -> None:
        """The evaluations that train replies carry: the clients' metrics for ``evaluated_round``, or
        why a client's evaluation failed (its training may still have counted)."""
        carried = [(msg.content[CLIENT], dict(msg.content[EVALUATION])) for msg in replies if EVALUATION in msg.content]
        failures = {int(client["index"]): str(e["error"]) for client, e in carried if "error" in e}
        contents = [
            RecordDict({"metrics": MetricRecord(e), CLIENT: client}) for client, e in carried if "error" not in e
        ]
        aggregate = self.evaluate_metrics_aggr_fn(contents, self.weighted_by_key) if contents else None
        if contents:
            logger.info(
                "Round {} client evaluation (sent with round {}): {}", evaluated_round, evaluated_round + 1, aggregate
            )
        if carried:
            self.observer.record_clients("evaluate", evaluated_round, contents, aggregate, failures)

    def configure_evaluate(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        server_round += self.round_offset
        if server_round != self.last_round:
            return []  # evaluated first thing in the next round's train message
        return super().configure_evaluate(
            server_round, encode(arrays.to_torch_state_dict(), self.wire_dtype), config, grid
        )

    def aggregate_evaluate(self, server_round: int, replies: Iterable[Message]) -> MetricRecord | None:
        server_round += self.round_offset
        replies = list(replies)
        if not replies:
            return None
        failures = {}
        for msg in (m for m in replies if m.has_error()):
            self._log_failure(server_round, msg)
            if (client := self.node_clients.get(msg.metadata.src_node_id)) is not None:
                failures[client] = msg.error.reason
        answered = [m for m in replies if not m.has_error()]  # the failures are logged once, above
        metrics = super().aggregate_evaluate(server_round, answered) if answered else None
        self.observer.record_clients("evaluate", server_round, [m.content for m in answered], metrics, failures)
        return metrics
