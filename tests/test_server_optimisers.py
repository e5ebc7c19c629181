"""Server optimisers on real Flower Messages: outer Nesterov against a hand-computed example, every
optimiser's state through a real checkpoint and back, and an outsized update bounded and named."""

from __future__ import annotations

import numpy as np
import pytest
from flwr.app import ArrayRecord, ConfigRecord
from loguru import logger

from tests.test_aggregation import Recorder, TwoNodes, arrays, reply
from zk0.artifacts.resume import find_resume_point
from zk0.artifacts.run_folder import save_checkpoint
from zk0.config import DEFAULT_SERVER_LR, SERVER_OPTIMISERS, ConfigError, from_run_config
from zk0.federation.aggregation import ValidatingStrategy
from zk0.federation.updates import array_signature
from zk0.federation.server_optimisers import STATE, make_strategy, restore_state

pytestmark = pytest.mark.usefixtures("flower_task")  # the tests play the ServerApp of run 1


def wrapped(name: str, lr: float = 0.0, momentum: float = 0.9, clip: float = 0.0) -> ValidatingStrategy:
    return ValidatingStrategy(
        make_strategy(name, lr, momentum, min_train_nodes=2),
        expected=array_signature(arrays(0.0)),
        evaluates_in=lambda _: False,
        observer=Recorder([]),
        last_round=10,
        proximal_mu=0.05,
        update_clip=clip,
    )


def train_round(strategy: ValidatingStrategy, server_round: int, start: ArrayRecord, moves: list[float]) -> ArrayRecord:
    """One round: both clients get ``start`` and move every weight by their ``moves``, equally weighted."""
    messages = list(strategy.configure_train(server_round, start, ConfigRecord({}), TwoNodes()))
    assert all(m.content["config"]["proximal-mu"] == 0.05 for m in messages), "FedProx's mu, whatever the optimiser"
    w = float(start["a"].numpy().flat[0])
    replies = [reply(i + 1, arrays(w + move, w + move), examples=10) for i, move in enumerate(moves)]
    result, _ = strategy.aggregate_train(server_round, replies)
    return result


def test_names_match_the_run_configs_choices():
    assert tuple(DEFAULT_SERVER_LR) == SERVER_OPTIMISERS == tuple(STATE)


def test_outer_nesterov_matches_a_hand_computed_two_round_example():
    """w0 = 1, lr 0.7, momentum 0.9. Round 1: the clients average 0.8, so g = 0.2, b = 0.2,
    w1 = 1 - 0.7 * (0.2 + 0.9 * 0.2) = 0.734. Round 2: they average w1 - 0.1, so g = 0.1,
    b = 0.9 * 0.2 + 0.1 = 0.28, w2 = 0.734 - 0.7 * (0.1 + 0.9 * 0.28) = 0.4876."""
    strategy = wrapped("nesterov", lr=0.7, momentum=0.9)
    w1 = train_round(strategy, 1, arrays(1.0, 1.0), [-0.15, -0.25])
    np.testing.assert_allclose(w1["a"].numpy(), 0.734, rtol=1e-6)
    w2 = train_round(strategy, 2, w1, [-0.1, -0.1])
    np.testing.assert_allclose(w2["b"].numpy(), 0.4876, rtol=1e-6)
    np.testing.assert_allclose(strategy.server_state()["momentum/a"], 0.28, rtol=1e-6)


def test_plain_averaging_and_unit_steps_agree():
    """Nesterov with lr 1 and momentum 0, FedAvgM likewise and FedAvg give the same average."""
    results = [train_round(wrapped(n, lr=1.0, momentum=0.0), 1, arrays(1.0), [0.2, 0.4]) for n in ("fedavg", "fedavgm")]
    results.append(train_round(wrapped("nesterov", lr=1.0, momentum=0.0), 1, arrays(1.0), [0.2, 0.4]))
    for result in results:
        np.testing.assert_allclose(result["a"].numpy(), 1.3, rtol=1e-6)


@pytest.mark.parametrize("name", SERVER_OPTIMISERS)
def test_each_optimisers_state_survives_a_checkpoint(name, tmp_path, client_parts):
    """Three rounds in one go equal two rounds, a checkpoint, a fresh strategy restored from it, and
    the third: momentum and moments come back, so the resumed run's model is the same."""
    moves = [[0.2, 0.4], [0.1, 0.3], [-0.05, 0.15]]
    straight = wrapped(name)
    model = arrays(1.0, 1.0)
    for server_round, move in enumerate(moves, start=1):
        model = train_round(straight, server_round, model, move)

    first = wrapped(name)
    resumed_from = arrays(1.0, 1.0)
    for server_round, move in enumerate(moves[:2], start=1):
        resumed_from = train_round(first, server_round, resumed_from, move)
    save_checkpoint(client_parts[0], tmp_path, 2, {}, server_state=(name, first.server_state()))
    (tmp_path / "server").mkdir()
    point = find_resume_point(str(tmp_path))
    assert point.server_optimiser == name
    assert set(point.server_state) == set(first.server_state())
    second = wrapped(name)
    restore_state(second.inner, point.server_state, list(second.expected), point.server_optimiser)
    again = train_round(second, 3, resumed_from, moves[2])
    for key in ("a", "b"):
        np.testing.assert_array_equal(again[key].numpy(), model[key].numpy())
    if STATE[name]:  # the restored state is what carried it: a fresh strategy would step differently
        fresh = train_round(wrapped(name), 3, resumed_from, moves[2])
        assert not np.array_equal(fresh["a"].numpy(), model["a"].numpy())


def test_another_optimisers_state_is_not_restored():
    messages = []
    sink = logger.add(lambda m: messages.append(m.record["message"]), level="WARNING")
    try:
        strategy = wrapped("fedadam")
        restore_state(strategy.inner, {"momentum/a": np.ones((2, 3), np.float32)}, ["a", "b"], "nesterov")
    finally:
        logger.remove(sink)
    assert strategy.inner.m_t is None or not strategy.inner.m_t
    assert messages == [
        "The checkpoint keeps server-optimiser='nesterov''s state and this run uses 'fedadam', which starts afresh."
    ]


def test_an_update_1000x_the_others_is_scaled_down_and_its_client_named():
    messages = []
    sink = logger.add(lambda m: messages.append(m.record["message"]), level="WARNING")
    strategy = wrapped("fedavg", clip=3.0)
    strategy.configure_train(4, arrays(0.0), ConfigRecord({}), TwoNodes())
    replies = [reply(node, arrays(move, move), examples=10) for node, move in ((1, 0.1), (2, 0.12), (3, 0.08))]
    replies.append(reply(4, arrays(100.0, 100.0), examples=10))  # a client sending 1000x the others' change
    try:
        result, metrics = strategy.aggregate_train(4, replies)
    finally:
        logger.remove(sink)
    (warning,) = messages
    assert warning.startswith("Round 4: client 4 (d4)'s update is 1e+03x the median of the others'")
    assert warning.endswith("above update-clip=3; scaled down to that median.")
    scales = [r.content["metrics"]["update-scale"] for r in replies]
    assert scales[:3] == [1.0, 1.0, 1.0] and scales[3] == pytest.approx(0.001, rel=1e-3)
    # the bad client now moves weights by the others' median (0.1), so the average is (0.3 + 0.1) / 4
    np.testing.assert_allclose(result["a"].numpy(), (0.1 + 0.12 + 0.08 + 0.1) / 4, rtol=1e-5)
    assert "update-norm" in metrics


def test_two_clients_bound_each_other():
    strategy = wrapped("fedavg", clip=3.0)
    strategy.configure_train(1, arrays(0.0), ConfigRecord({}), TwoNodes())
    result, _ = strategy.aggregate_train(1, [reply(1, arrays(0.1, 0.1), 10), reply(2, arrays(100.0, 100.0), 10)])
    np.testing.assert_allclose(result["a"].numpy(), (0.1 + 0.1) / 2, rtol=1e-5)


@pytest.mark.parametrize(
    ("overrides", "sentence"),
    [
        (
            {"server-optimiser": "adam"},
            "Run-config key 'server-optimiser' got 'adam'; expected one of "
            "['fedavg', 'fedavgm', 'nesterov', 'fedadam', 'fedyogi'].",
        ),
        (
            {"server-optimiser": "fedavg", "server-lr": 0.5},
            "Run-config key 'server-lr' got 0.5, and server-optimiser='fedavg' takes the average",
        ),
        ({"server-momentum": 1.0}, "Run-config key 'server-momentum' got 1.0; expected a value >= 0 and <= 0.99."),
        ({"update-clip": 0.5}, "Run-config key 'update-clip' got 0.5; expected 0 (off) or a factor >= 1"),
    ],
)
def test_bad_server_optimiser_settings_are_refused_in_one_sentence(overrides, sentence):
    with pytest.raises(ConfigError) as refused:
        from_run_config(overrides)
    assert str(refused.value).startswith(sentence)
