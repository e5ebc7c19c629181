"""zk0's additions to whichever Flower strategy a run picks, by composition.

``ValidatingStrategy`` wraps a Flower strategy of the FedAvg family (the server optimiser the
run chose: zk0.federation.server_optimisers) and lets it sample, average and step as it does. Around it,
it adds what a federation of robot owners needs: replies whose arrays are non-finite or do
not match the global model's names/shapes/dtypes are rejected and logged, not averaged; an
update more than ``update-clip`` times the others' median size is scaled down to that median
(one client's broken normalisation, bug or scaled update cannot wreck the model); with
``aggregation`` a robust rule of Flower's or ByzFL's combines the updates instead of the mean
(zk0.federation.robust), and with ``dp = "owner"`` Flower's DP mechanism clips, averages and noises them
(zk0.federation.privacy); either way the wrapped strategy's server optimiser steps from the result; FedProx's
``proximal-mu`` goes into every train config, whatever the optimiser; federated evaluation runs
every ``eval-frequency`` rounds; a round that finds too few owners connected says so and, after
``wait-for-owners-s``, ends the run with a checkpoint to resume from (zk0.federation.waiting); a resumed
run keeps its round numbers; and each client's own
metrics and dataset statistics, and the end of every round, go to an observer
(zk0.federation.round_artifacts) that writes them.

Federated evaluation rides on the next round's train message: the model a client receives
for round N+1 is the one round N produced, so it evaluates that first and reports it as round
N's evaluation. On a SuperNode every message costs a process start and two polls of Flower's
(seconds each), so one message per client and round instead of two halves that cost. Only the
last round's model, which no train message follows, gets an evaluate message of its own.
"""

from __future__ import annotations

import random
import statistics
from collections.abc import Callable, Iterable
from typing import Protocol

import numpy as np
from flwr.app import Array, ArrayRecord, ConfigRecord, Message, MetricRecord, RecordDict
from flwr.serverapp import Grid
from flwr.serverapp.strategy import FedAvg, Strategy
from loguru import logger

from zk0.common.errors import REFUSED, Zk0Error
from zk0.federation.privacy import OwnerLevelDP, PrivacyBudgetSpent
from zk0.federation.robust import ByzflRule, combine, rule_name
from zk0.federation.server_optimisers import optimiser_name, optimiser_state
from zk0.federation.updates import scaled_update, steps_taken, update_norm, update_problem
from zk0.federation.waiting import OwnersGone, OwnersWatch
from zk0.federation.wire import CLIENT, EVALUATE_ROUND, EVALUATION, KEEP_STATE, decode, encode


class RoundObserver(Protocol):
    """Who keeps the rounds (zk0.federation.round_artifacts.RoundArtifacts)."""

    def record_clients(
        self,
        phase: str,
        server_round: int,
        replies: list[RecordDict],
        aggregate: MetricRecord | None,
        failures: dict[int, str],
    ) -> None:
        """A phase's replies that counted, their weighted aggregate, failed clients' reasons by index."""

    def record_late(self, server_round: int, clients: list[int], nodes: list[int]) -> None:
        """Sampled clients (by dataset index; ``nodes``: ids of nodes that never replied yet) whose
        train reply did not arrive within the round's deadline: their updates were not counted."""

    def round_ended(
        self,
        server_round: int,
        arrays: ArrayRecord,
        evaluation: MetricRecord | None,
        server_state: dict[str, np.ndarray],
    ) -> None:
        """The round is over: ``arrays`` is the global model, ``evaluation`` the server's of it,
        ``server_state`` what the server optimiser carries into the next round."""

    def record_privacy(self, server_round: int, spent: dict) -> None:
        """The privacy the run has spent once this round's model was released (``OwnerLevelDP.spent``)."""

    def checkpoint(
        self,
        server_round: int,
        arrays: ArrayRecord,
        evaluation: MetricRecord | None,
        server_state: dict[str, np.ndarray],
    ):
        """Keep this round's model as a checkpoint to resume from (a round the run ends early in)."""


class RunCannotTrain(Zk0Error):
    """The run's first round produced too few updates to train anything."""


class ValidatingStrategy(Strategy):
    """A Flower strategy (``inner``) that rejects malformed updates, bounds outsized ones and
    records each client's reply; sampling, averaging and the server's step stay ``inner``'s."""

    def __init__(
        self,
        inner: FedAvg,
        *,
        expected: dict[str, tuple[tuple[int, ...], str]],
        evaluates_in: Callable[[int], bool],
        observer: RoundObserver,
        checkpoints_in: Callable[[int], bool] = lambda _: False,
        last_round: int,
        round_offset: int = 0,
        wire_dtype: str = "float32",
        proximal_mu: float = 0.0,
        update_clip: float = 0.0,
        averaging: str = "samples",
        privacy: OwnerLevelDP | None = None,
        rule: FedAvg | ByzflRule | None = None,
        owners: OwnersWatch | None = None,
    ) -> None:
        self.inner = inner
        self.expected = expected
        self.wire_dtype = wire_dtype  # the global model is kept in fp32; messages carry this dtype
        self.evaluates_in = evaluates_in
        self.checkpoints_in = checkpoints_in  # clients keep their training state in these rounds
        self.observer = observer
        self.last_round = last_round  # of the whole run, resumed rounds included
        self.round_offset = round_offset  # rounds a resumed run already has: Flower counts from 1 again
        self.proximal_mu = proximal_mu
        self.update_clip = update_clip  # an update above this times the others' median norm is scaled to it; 0 = off
        self.averaging = averaging  # updates of unequal steps: "fednova" (normalised by steps) or "samples"
        self.privacy = privacy  # owner-level DP: Flower's clip, mean and noise replace update-clip and the weights
        self.rule = rule  # Flower's or ByzFL's robust rule (zk0.federation.robust) in place of the mean; None: the mean
        self.owners = owners  # watches Flower's wait for enough connected owners; None: Flower's wait alone
        self.current: ArrayRecord | None = None  # the global model this round's updates start from
        self.evaluation: MetricRecord | None = None  # the server's evaluation of the latest round's model
        self.sampled: set[int] = set()  # nodes asked to train this round
        self.sent: list[Message] = []  # this round's train instructions (the grid gives each its id as it sends it)
        self.node_clients: dict[int, int] = {}  # node id -> client (dataset) index, from their replies

    def summary(self) -> None:
        logger.info(
            "Server optimiser {} with proximal-mu {}, update-clip {}, {}",
            optimiser_name(self.inner),
            self.proximal_mu,
            "replaced by owner-level DP's clip" if self.privacy else self.update_clip or "off",
            f"aggregation {rule_name(self.rule)}" if self.rule else "the weighted mean",
        )
        if self.privacy:
            self.privacy.mechanism.summary()
        self.inner.summary()

    def server_state(self) -> dict[str, np.ndarray]:
        """What the server optimiser carries into the next round (kept with each checkpoint)."""
        return optimiser_state(self.inner, list(self.expected))

    def start(self, *, evaluate_fn: Callable[[int, ArrayRecord], MetricRecord | None] | None = None, **kwargs):
        """Flower's round loop, run as it is. ``evaluate_fn`` (the server's evaluation, the last step
        of Flower's round) gets the run's round numbers, and after it the observer is told the
        round ended; a resumed run's round 0 is its last checkpoint, evaluated and kept before."""

        def evaluate_and_end_round(flower_round: int, arrays: ArrayRecord) -> MetricRecord | None:
            if flower_round == 0 and self.round_offset:
                return None
            server_round = flower_round + self.round_offset
            evaluation = evaluate_fn(server_round, arrays) if evaluate_fn else None
            self.evaluation = evaluation
            self.observer.round_ended(server_round, arrays, evaluation, self.server_state())
            if server_round and server_round < self.last_round and self.privacy and self.privacy.would_exceed():
                self.stop_within_budget(server_round, arrays, evaluation)
            return evaluation

        return super().start(evaluate_fn=evaluate_and_end_round, **kwargs)

    def stop_within_budget(self, server_round: int, arrays: ArrayRecord, evaluation: MetricRecord | None) -> None:
        """End the run after ``server_round``, the last release that fits ``dp-epsilon-budget``: its
        model is kept as a checkpoint (a resumed run with a larger budget continues from it)."""
        if not self.checkpoints_in(server_round):
            self.observer.checkpoint(server_round, arrays, evaluation, self.server_state())
        spent = self.privacy.spent()
        raise PrivacyBudgetSpent(
            f"Round {server_round} spent epsilon {spent['epsilon']:.3g} at delta {spent['delta']:g}, and round "
            f"{server_round + 1} would take it to {self.privacy.epsilon_after(1):.3g}, past dp-epsilon-budget="
            f"{spent['budget']:g}; the run ends here with round {server_round}'s model kept as a checkpoint."
        )

    def configure_train(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        server_round += self.round_offset
        self.current = arrays
        privacy = {"dp-epsilon-spent": self.privacy.spent()["epsilon"]} if self.privacy else {}
        config = ConfigRecord(
            {**config, "proximal-mu": self.proximal_mu, KEEP_STATE: self.checkpoints_in(server_round), **privacy}
        )  # FedProx's key, for any optimiser; a checkpoint round's clients keep their state to resume from
        try:
            messages = list(self.inner.configure_train(server_round, arrays, config, self._watched(grid, server_round)))
        except OwnersGone as err:
            raise OwnersGone(f"{err}; {self.keep_for_resume(server_round - 1, arrays)}") from None
        wire = encode(arrays.to_torch_state_dict(), self.wire_dtype)
        for msg in messages:  # the optimiser keeps the fp32 model; clients get the wire dtype
            msg.content[self.inner.arrayrecord_key] = wire
        self.sampled = {msg.metadata.dst_node_id for msg in messages}
        self.sent = messages
        previous = server_round - 1
        if previous > self.round_offset and self.evaluates_in(previous):
            self._evaluate_first(messages, previous)
        return messages

    def _watched(self, grid: Grid, server_round: int) -> Grid:
        return self.owners.watching(grid, server_round) if self.owners else grid

    def keep_for_resume(self, previous: int, arrays: ArrayRecord) -> str:
        """Before the run ends for want of owners: round ``previous``'s model (``arrays``) kept as a
        checkpoint, if no checkpoint holds it yet; what was kept, as the end of a sentence."""
        if previous == 0:
            return "no round has trained, so there is nothing to resume: start the run again once they are connected"
        if previous > self.round_offset and not self.checkpoints_in(previous):
            self.observer.checkpoint(previous, arrays, self.evaluation, self.server_state())
        return f"the run ends here with round {previous}'s model kept as a checkpoint"

    def _evaluate_first(self, messages: list[Message], previous: int) -> None:
        """Ask a ``fraction-evaluate`` sample of the training clients to evaluate round ``previous`` first."""
        inner = self.inner
        count = min(len(messages), max(inner.min_evaluate_nodes, int(len(messages) * inner.fraction_evaluate)))
        for msg in random.sample(messages, count) if inner.fraction_evaluate > 0 else []:
            config = ConfigRecord({**msg.content[inner.configrecord_key], EVALUATE_ROUND: previous})
            msg.content = RecordDict({**msg.content, inner.configrecord_key: config})

    def _log_missing(self, server_round: int, valid: list[Message], replies: list[Message]) -> None:
        """Name every sampled node whose update did not arrive (crashed, offline, rejected); a node
        that replied with an error was named with its reason already."""
        failed = {self.node_of(msg) for msg in replies if msg.has_error()}
        for node in sorted(self.sampled - {msg.metadata.src_node_id for msg in valid} - failed):
            who = self._named(node)
            logger.warning("Round {}: no usable update from node {} ({}); aggregating the others.", server_round, node, who)

    def _record_late(self, server_round: int, replies: list[Message]) -> None:
        """The sampled nodes that sent no reply at all (a failed one sends its error): past the
        round's deadline (or the phase timeout), their update is dropped; the observer names them."""
        late = sorted(self.sampled - {self.node_of(msg) for msg in replies})
        if late:
            clients = sorted(self.node_clients[n] for n in late if n in self.node_clients)
            self.observer.record_late(server_round, clients, [n for n in late if n not in self.node_clients])

    def valid_updates(self, server_round: int, replies: Iterable[Message]) -> list[Message]:
        """Replies that may be averaged; every other one is logged with its reason."""
        valid = []
        for msg in replies:
            if msg.has_error():
                self._log_failure(server_round, msg)
                continue
            try:  # averaged in fp32, whatever travelled
                msg.content[self.inner.arrayrecord_key] = ArrayRecord(
                    decode(msg.content[self.inner.arrayrecord_key], self.wire_dtype)
                )
            except Zk0Error as err:
                logger.warning(
                    "Round {}: rejected the update of node {}: {}", server_round, msg.metadata.src_node_id, err
                )
                continue
            problem = update_problem(msg.content[self.inner.arrayrecord_key], self.expected)
            if problem:
                logger.warning(
                    "Round {}: rejected the update of node {}: {}", server_round, msg.metadata.src_node_id, problem
                )
                continue
            valid.append(msg)
            if CLIENT in msg.content:
                self.node_clients[msg.metadata.src_node_id] = int(msg.content[CLIENT]["index"])
        return valid

    def node_of(self, reply: Message) -> int:
        """The node a reply answers for. The SuperLink answers for a node that went away (its
        heartbeat stopped) with an error from the SuperLink itself; the message it replies to says
        which node that was."""
        asked = {msg.metadata.message_id: msg.metadata.dst_node_id for msg in self.sent if msg.metadata.message_id}
        return asked.get(reply.metadata.reply_to_message_id or None, reply.metadata.src_node_id)

    def _named(self, node: int) -> str:
        client = self.node_clients.get(node)
        return f"client {client}" if client is not None else "a client that has sent no update yet"

    def _log_failure(self, server_round: int, msg: Message) -> None:
        """A client's refusal is its own sentence (it names the client and dataset); anything else
        comes from Flower or a crash and is named by node and client, once."""
        if msg.error.code == REFUSED:
            logger.error("Round {}: {}", server_round, msg.error.reason)
        else:
            node = self.node_of(msg)
            who, reason = self._named(node), msg.error.reason
            logger.warning("Round {}: no usable update from node {} ({}): {}", server_round, node, who, reason)

    def aggregate_train(
        self, server_round: int, replies: Iterable[Message]
    ) -> tuple[ArrayRecord | None, MetricRecord | None]:
        server_round += self.round_offset
        replies = list(replies)
        valid = self.valid_updates(server_round, replies)
        self._log_missing(server_round, valid, replies)
        self._record_late(server_round, replies)
        self._record_evaluation(server_round - 1, valid)
        if len(valid) < self.inner.min_train_nodes and server_round == self.round_offset + 1:
            raise RunCannotTrain(
                f"Round {server_round} got {len(valid)} usable update(s), fewer than min-train-clients="
                f"{self.inner.min_train_nodes}, so this run cannot train; the clients' reasons are above."
            )
        if len(valid) < self.inner.min_train_nodes:
            logger.warning(
                "Round {}: {} valid updates, fewer than min-train-clients={}; the global model is kept.",
                server_round,
                len(valid),
                self.inner.min_train_nodes,
            )
            self.observer.record_clients("train", server_round, [m.content for m in valid], None, {})
            return None, None
        current = {name: array.numpy() for name, array in self.current.items()}  # decoded once, not per client
        if self.privacy:
            self.record_norms(valid, current, self.privacy.clip)
            self.replace_updates(valid, self.privacy.release(server_round, valid, self.current))
            self.observer.record_privacy(server_round, self.privacy.spent())
        else:
            self.bound_updates(server_round, valid, current)
            if self.averaging == "fednova":
                self.normalise_steps(server_round, valid, current)
            if self.rule is not None:
                combined = combine(self.rule, server_round, valid, current, self.inner.arrayrecord_key)
                if combined is None:
                    self.observer.record_clients("train", server_round, [m.content for m in valid], None, {})
                    return None, None
                self.replace_updates(valid, combined)
        arrays, metrics = self.inner.aggregate_train(server_round, valid)
        self.observer.record_clients("train", server_round, [m.content for m in valid], metrics, {})
        return arrays, metrics

    def bound_updates(self, server_round: int, valid: list[Message], current: dict[str, np.ndarray]) -> None:
        """Scale every update whose size (L2 norm of its change to the global model; with FedNova's
        averaging, per local step) is above ``update-clip`` times the median of the other updates'
        sizes down to that median, naming the client: past the clip an update is not trusted, so it
        counts as a typical one, no more (a client that took four times the steps is not an outlier
        for that). Each reply's metrics get its ``update-norm`` and the ``update-scale`` applied (1:
        untouched)."""
        key = self.inner.arrayrecord_key
        norms = [update_norm(msg.content[key], current) for msg in valid]
        per_step = self.averaging == "fednova"
        sizes = [n / steps_taken(msg) if per_step else n for n, msg in zip(norms, valid, strict=True)]
        for i, msg in enumerate(valid):
            typical = statistics.median(sizes[:i] + sizes[i + 1 :]) if len(sizes) > 1 else 0.0
            scale = typical / sizes[i] if self.update_clip and 0 < typical * self.update_clip < sizes[i] else 1.0
            if scale < 1:
                msg.content[key] = scaled_update(msg.content[key], current, scale)
                logger.warning(
                    "Round {}: {}'s update is {:.3g}x the median of the others' ({:.4g} against {:.4g}{}), above "
                    "update-clip={:g}; scaled down to that median.",
                    server_round,
                    self._who(msg),
                    sizes[i] / typical,
                    sizes[i],
                    typical,
                    " a step" if per_step else "",
                    self.update_clip,
                )
            (metrics,) = msg.content.metric_records.values()
            metrics["update-norm"], metrics["update-scale"] = norms[i], scale

    def record_norms(self, valid: list[Message], current: dict[str, np.ndarray], clip: float) -> None:
        """Each reply's ``update-norm`` and the ``update-scale`` a fixed clip at ``clip`` gives it."""
        for msg in valid:
            norm = update_norm(msg.content[self.inner.arrayrecord_key], current)
            (metrics,) = msg.content.metric_records.values()
            metrics["update-norm"], metrics["update-scale"] = norm, min(1.0, clip / norm) if norm else 1.0

    def replace_updates(self, valid: list[Message], combined: ArrayRecord) -> None:
        """Every reply's arrays become ``combined`` (the noisy mean, a robust rule's combination), so
        the server optimiser's weighted average of them is it, and it steps from there."""
        for msg in valid:
            msg.content[self.inner.arrayrecord_key] = combined

    def normalise_steps(self, server_round: int, valid: list[Message], current: dict[str, np.ndarray]) -> None:
        """FedNova's normalised averaging (Wang et al. 2020) when the clients took different steps.

        Averaging raw updates weights each client by the steps it took as well as by its samples,
        so with a time budget the fastest machines' data pull the model toward themselves. FedNova
        divides each update by its steps τ_k, averages those with the clients' sample weights p_k
        (the samples a client trains per step: what its weight is when everyone takes every step),
        and scales the average by τ_eff = Σ p_k τ_k: every client's data count as much as with
        equal work. The result replaces every reply's arrays, so the wrapped strategy's weighted
        average is it whatever the weights, and the server optimiser steps from it as before.
        Each reply's metrics get the ``step-scale`` τ_eff / τ_k its update was given."""
        steps = [steps_taken(msg) for msg in valid]
        if len(set(steps)) < 2:
            return  # equal work: the plain weighted average is FedNova's
        key = self.inner.arrayrecord_key
        metrics = [next(iter(msg.content.metric_records.values())) for msg in valid]
        weights = np.array([float(m[self.inner.weighted_by_key]) / tau for m, tau in zip(metrics, steps, strict=True)])
        weights /= weights.sum()
        tau_eff = float(np.dot(weights, steps))
        scales = [tau_eff / tau for tau in steps]
        averaged = {name: np.zeros_like(start) for name, start in current.items()}
        for msg, weight, scale in zip(valid, weights, scales, strict=True):
            for name, start in current.items():
                averaged[name] += weight * scale * (msg.content[key][name].numpy() - start)
        self.replace_updates(
            valid, ArrayRecord({name: Array(current[name] + change) for name, change in averaged.items()})
        )
        for m, scale in zip(metrics, scales, strict=True):
            m["step-scale"] = scale
        logger.info(
            "Round {}: the clients took {}-{} local steps; averaged with FedNova (mean steps {:.1f}).",
            server_round,
            min(steps),
            max(steps),
            tau_eff,
        )

    def _who(self, msg: Message) -> str:
        """``client 2 (synth-so100-stacking)``, or the node id of a reply that does not say."""
        if CLIENT not in msg.content:
            return f"node {msg.metadata.src_node_id}"
        client = msg.content[CLIENT]
        return f"client {int(client['index'])} ({client['dataset']})"

    def _record_evaluation(self, evaluated_round: int, replies: list[Message]) -> None:
        """The evaluations that train replies carry: the clients' metrics for ``evaluated_round``, or
        why a client's evaluation failed (its training may still have counted)."""
        carried = [(msg.content[CLIENT], dict(msg.content[EVALUATION])) for msg in replies if EVALUATION in msg.content]
        failures = {int(client["index"]): str(e["error"]) for client, e in carried if "error" in e}
        contents = [
            RecordDict({"metrics": MetricRecord(e), CLIENT: client}) for client, e in carried if "error" not in e
        ]
        aggregate = self.inner.evaluate_metrics_aggr_fn(contents, self.inner.weighted_by_key) if contents else None
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
        wire = encode(arrays.to_torch_state_dict(), self.wire_dtype)
        try:
            return self.inner.configure_evaluate(server_round, wire, config, self._watched(grid, server_round))
        except OwnersGone as err:  # the server's evaluation and the last checkpoint still follow
            logger.warning("{}; the owners do not evaluate the last round's model.", err)
            return []

    def aggregate_evaluate(self, server_round: int, replies: Iterable[Message]) -> MetricRecord | None:
        server_round += self.round_offset
        replies = list(replies)
        if not replies:
            return None
        failures = {}
        for msg in (m for m in replies if m.has_error()):
            self._log_failure(server_round, msg)
            if (client := self.node_clients.get(self.node_of(msg))) is not None:
                failures[client] = msg.error.reason
        answered = [m for m in replies if not m.has_error()]  # the failures are logged once, above
        metrics = self.inner.aggregate_evaluate(server_round, answered) if answered else None
        self.observer.record_clients("evaluate", server_round, [m.content for m in answered], metrics, failures)
        return metrics
