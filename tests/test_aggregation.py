"""Update validation and FedAvg weighting, on real Flower Messages."""

from __future__ import annotations

import numpy as np
import pytest
from flwr.app import ArrayRecord, ConfigRecord, Error, Message, MessageType, MetricRecord, RecordDict
from loguru import logger

from zk0.common.errors import REFUSED
from zk0.federation.aggregation import RunCannotTrain, ValidatingStrategy
from zk0.federation.updates import array_signature, update_problem
from zk0.federation.server_optimisers import make_strategy
from zk0.federation.wire import MANIFEST, PACKED, encode

pytestmark = pytest.mark.usefixtures("flower_task")  # the tests play the ServerApp of run 1


def arrays(a: float, b: float = 0.0, a_shape=(2, 3)) -> ArrayRecord:
    import torch

    return ArrayRecord({"a": torch.full(a_shape, a), "b": torch.full((4,), b)})


def reply(node: int, record: ArrayRecord, examples: int, steps: int = 1) -> Message:
    """A client's train reply carrying ``record`` (per tensor, fp32 or already packed) as zk0 sends it,
    after ``steps`` local steps."""
    if set(record) != {PACKED, MANIFEST}:
        record = encode(record.to_torch_state_dict(), "float32")
    instruction = Message(
        content=RecordDict({"arrays": arrays(0.0), "config": ConfigRecord({})}),
        dst_node_id=node,
        message_type=MessageType.TRAIN,
    )
    metrics = MetricRecord({"num-examples": examples, "local-steps": steps, "train-loss": float(node)})
    client = ConfigRecord({"index": node, "dataset": f"d{node}"})
    return Message(content=RecordDict({"arrays": record, "metrics": metrics, "client": client}), reply_to=instruction)


def failed(node: int) -> Message:
    instruction = Message(content=RecordDict({}), dst_node_id=node, message_type=MessageType.TRAIN)
    return Message(Error(code=0, reason="client crashed"), reply_to=instruction)


class Recorder:
    """The strategy's observer, keeping what it is told."""

    def __init__(self, recorded: list):
        self.recorded = recorded

    def record_clients(self, phase, rnd, replies, aggregate, failures):
        self.recorded.append((phase, rnd, len(replies), aggregate, failures))

    def round_ended(self, rnd, arrays, evaluation, server_state):
        self.recorded.append(("ended", rnd, evaluation))


@pytest.fixture
def strategy():
    return validating()


def validating(averaging: str = "fednova", update_clip: float = 0.0) -> ValidatingStrategy:
    """zk0's strategy around plain averaging, as a round's replies meet it."""
    recorded = []
    strat = ValidatingStrategy(
        make_strategy("fedavg", 0.0, 0.9, min_train_nodes=2),
        averaging=averaging,
        update_clip=update_clip,
        expected=array_signature(arrays(0.0)),
        evaluates_in=lambda rnd: rnd % 2 == 0,
        observer=Recorder(recorded),
        last_round=4,
        proximal_mu=0.01,
    )
    strat.current = arrays(0.0)  # the global model the replies started from (configure_train sets it)
    strat.recorded = recorded
    return strat


def test_update_problems_are_named():
    expected = array_signature(arrays(0.0))
    assert update_problem(arrays(1.0), expected) is None
    assert "NaN" in update_problem(arrays(float("nan")), expected)
    assert "infinite" in update_problem(arrays(0.0, float("inf")), expected)
    assert "expected float32[2, 3]" in update_problem(arrays(1.0, a_shape=(3, 2)), expected)
    assert "missing ['b']" in update_problem(ArrayRecord({"a": arrays(1.0)["a"]}), expected)


def test_average_is_weighted_by_samples_and_skips_bad_updates(strategy):
    replies = [
        reply(1, arrays(1.0, 10.0), examples=10),
        reply(2, arrays(4.0, 40.0), examples=30),
        reply(3, arrays(float("nan")), examples=1000),
        reply(4, arrays(9.0, a_shape=(3, 2)), examples=1000),
        failed(5),
    ]
    result, metrics = strategy.aggregate_train(1, replies)
    assert result is not None, "the round completes with the two valid updates"
    np.testing.assert_allclose(result["a"].numpy(), np.full((2, 3), (1 * 10 + 4 * 30) / 40))
    np.testing.assert_allclose(result["b"].numpy(), np.full(4, (10 * 10 + 40 * 30) / 40))
    assert metrics["train-loss"] == pytest.approx((1 * 10 + 2 * 30) / 40)
    assert strategy.recorded == [("train", 1, 2, metrics, {})]


def test_too_few_valid_updates_after_round_1_keep_the_global_model(strategy):
    result, metrics = strategy.aggregate_train(2, [reply(1, arrays(1.0), 10), reply(2, arrays(float("nan")), 10)])
    assert (result, metrics) == (None, None)
    assert strategy.recorded == [("train", 2, 1, None, {})]


def refused(node: int, reason: str) -> Message:
    instruction = Message(content=RecordDict({}), dst_node_id=node, message_type=MessageType.TRAIN)
    return Message(Error(code=REFUSED, reason=reason), reply_to=instruction)


def test_a_first_round_without_enough_updates_stops_the_run_with_each_clients_sentence(strategy):
    messages = []
    sink = logger.add(lambda m: messages.append(m.record["message"]), level="WARNING")
    try:
        with pytest.raises(RunCannotTrain) as stopped:
            strategy.aggregate_train(1, [refused(1, "Client 0 (a): Dataset 'a' records no camera."), failed(2)])
    finally:
        logger.remove(sink)
    assert str(stopped.value) == (
        "Round 1 got 0 usable update(s), fewer than min-train-clients=2, so this run cannot train; "
        "the clients' reasons are above."
    )
    assert messages == [
        "Round 1: Client 0 (a): Dataset 'a' records no camera.",
        "Round 1: no usable update from node 2 (a client that has sent no update yet): client crashed",
    ]
    assert strategy.recorded == [], "nothing is recorded as if the round had trained"


class TwoNodes:
    """The part of Flower's Grid that sampling reads."""

    def get_node_ids(self):
        return [1, 2]


def test_a_node_the_superlink_answers_for_is_named_once_by_its_own_node_and_client(strategy):
    """A SuperNode whose heartbeat stopped gets an error reply from the SuperLink itself (from node
    1, Flower's SUPERLINK_NODE_ID): the message it answers says the node, and the server names that
    node and its client once, with the reason, not as a straggler."""
    from flwr.common.constant import SUPERLINK_NODE_ID

    strategy.aggregate_train(1, [reply(1, arrays(1.0), 10), reply(2, arrays(1.0), 10)])  # node 2 is client 2
    sent = list(strategy.configure_train(2, arrays(0.0), ConfigRecord({}), TwoNodes()))
    for index, msg in enumerate(sent):  # as Flower's grid does when it sends them
        msg.metadata.__dict__["_message_id"] = f"m{index}"
    to_two = next(m for m in sent if m.metadata.dst_node_id == 2)
    unavailable = Message(Error(code=0, reason="Node Unavailable"), reply_to=to_two)
    unavailable.metadata.__dict__["_src_node_id"] = SUPERLINK_NODE_ID
    assert unavailable.metadata.src_node_id == SUPERLINK_NODE_ID
    messages, late = [], []
    strategy.observer.record_late = lambda rnd, clients, nodes: late.append((rnd, clients, nodes))
    sink = logger.add(lambda m: messages.append(m.record["message"]), level="WARNING")
    try:
        strategy.aggregate_train(2, [reply(1, arrays(1.0), 10), unavailable])
    finally:
        logger.remove(sink)
    assert messages[0] == "Round 2: no usable update from node 2 (client 2): Node Unavailable"
    assert not any("node 1" in m or "(client 2); aggregating" in m for m in messages), messages
    assert late == []


def test_client_evaluation_rides_on_the_next_train_message_and_only_the_last_round_has_its_own(strategy):
    def evaluate_round(server_round: int) -> list:
        messages = strategy.configure_train(server_round, arrays(0.0), ConfigRecord({}), TwoNodes())
        return [msg.content["config"].get("evaluate-round") for msg in messages]

    assert evaluate_round(1) == [None, None], "nothing came before round 1"
    assert evaluate_round(2) == [None, None], "round 1 is not on the eval schedule"
    assert evaluate_round(3) == [2, 2], "round 3's train messages evaluate round 2's model first"
    assert list(strategy.configure_evaluate(2, arrays(0.0), ConfigRecord({}), TwoNodes())) == []
    last = list(strategy.configure_evaluate(4, arrays(0.0), ConfigRecord({}), TwoNodes()))
    assert [msg.metadata.message_type for msg in last] == [MessageType.EVALUATE] * 2


def test_evaluations_carried_by_train_replies_are_recorded_for_the_round_they_evaluate(strategy):
    replies = [reply(1, arrays(1.0), 10), reply(2, arrays(3.0), 30)]
    for msg, mse in zip(replies, (1.0, 5.0), strict=True):
        msg.content["evaluation"] = ConfigRecord({"action-mse": mse, "num-examples": 4 * mse})
    strategy.aggregate_train(3, replies)
    phase, evaluated, count, aggregate, failures = strategy.recorded[0]
    assert (phase, evaluated, count, failures) == ("evaluate", 2, 2, {})
    assert aggregate["action-mse"] == pytest.approx((1.0 * 4 + 5.0 * 20) / 24), "weighted by examples evaluated"
    assert strategy.recorded[1][:3] == ("train", 3, 2)


def test_a_failed_client_evaluation_is_recorded_with_its_reason_and_training_still_counts(strategy):
    replies = [reply(1, arrays(1.0), 10), reply(2, arrays(3.0), 30)]
    replies[0].content["evaluation"] = ConfigRecord({"action-mse": 2.0, "num-examples": 8})
    reason = "Client 2 (b): Dataset 'b': 3 of 3 held-out batches could not be decoded, more than max-skip-fraction=0.1."
    replies[1].content["evaluation"] = ConfigRecord({"error": reason})
    result, _ = strategy.aggregate_train(3, replies)
    np.testing.assert_allclose(result["a"].numpy(), np.full((2, 3), (1.0 * 10 + 3.0 * 30) / 40))
    assert strategy.recorded[1][:3] == ("train", 3, 2)
    phase, evaluated, count, aggregate, failures = strategy.recorded[0]
    assert (phase, evaluated, count, failures) == ("evaluate", 2, 1, {2: reason})
    assert aggregate["action-mse"] == pytest.approx(2.0)


def test_fednova_counts_every_clients_data_alike_whatever_steps_it_took():
    """Two clients from a global model at 0, as a time budget leaves them: client 1 took 2 steps
    (batch 8: 16 samples) to 2.0, client 2 took 6 (48 samples) to -3.0. FedNova: per step +1.0 and
    -0.5, weights 8/8 per step (one half each), mean steps 4: 0 + 4 * (0.5 * 1.0 + 0.5 * -0.5) = 1.0.
    Plain sample weighting: (16 * 2 - 48 * 3) / 64 = -1.75, pulled toward the client that took more
    steps. With equal steps the two are the same average."""
    replies = [reply(1, arrays(2.0, 4.0), examples=16, steps=2), reply(2, arrays(-3.0, 0.0), examples=48, steps=6)]
    nova, _ = validating("fednova").aggregate_train(1, replies)
    np.testing.assert_allclose(nova["a"].numpy(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(nova["b"].numpy(), 4 * (0.5 * 4.0 / 2 + 0.5 * 0.0 / 6), rtol=1e-6)
    scales = [next(iter(m.content.metric_records.values()))["step-scale"] for m in replies]
    assert scales == pytest.approx([4 / 2, 4 / 6])

    replies = [reply(1, arrays(2.0, 4.0), examples=16, steps=2), reply(2, arrays(-3.0, 0.0), examples=48, steps=6)]
    samples, _ = validating("samples").aggregate_train(1, replies)
    np.testing.assert_allclose(samples["a"].numpy(), (16 * 2.0 - 48 * 3.0) / 64, rtol=1e-6)

    equal = lambda: [reply(1, arrays(2.0), examples=16, steps=2), reply(2, arrays(-3.0), examples=48, steps=2)]  # noqa: E731
    same = [validating(averaging).aggregate_train(1, equal())[0]["a"].numpy() for averaging in ("fednova", "samples")]
    np.testing.assert_array_equal(same[0], same[1])


def test_with_fednova_a_client_that_took_more_steps_is_not_clipped_for_it():
    """update-clip compares updates per step under FedNova: four times the steps and four times
    the change is a typical update; four times the change in the same steps is not."""
    replies = [reply(1, arrays(1.0), 8, steps=1), reply(2, arrays(1.1), 8, steps=1), reply(3, arrays(4.0), 32, steps=4)]
    validating("fednova", update_clip=3.0).aggregate_train(1, replies)
    assert [next(iter(m.content.metric_records.values()))["update-scale"] for m in replies] == [1.0, 1.0, 1.0]
    replies = [reply(1, arrays(1.0), 8, steps=4), reply(2, arrays(1.1), 8, steps=4), reply(3, arrays(4.0), 32, steps=4)]
    validating("fednova", update_clip=3.0).aggregate_train(1, replies)
    clipped = next(iter(replies[2].content.metric_records.values()))["update-scale"]
    assert clipped == pytest.approx(1.05 / 4.0, rel=1e-3)  # to the median of the others' sizes
