"""The deployment benchmark's arithmetic on a run's metric history (zk0.bench.deployment)."""

from __future__ import annotations

import pytest

from zk0.bench.deployment import fixed_cost_figures, fixed_costs, message_breakdown


def round_record(number: int, wall: float, server_eval: float, train: dict, evaluate: dict) -> dict:
    return {
        "round": number,
        "wall-s": wall,
        "server-evaluate": {"eval-s": server_eval},
        "clients": {"0": {"train": train, "evaluate": evaluate}},
    }


def train(step: float, evaluate_s: float) -> dict:
    return {
        "step-time": step, "evaluate-s": evaluate_s, "startup-s": 3.0, "handler-s": 2 * step + evaluate_s + 1.0,
        "worker-s": 2 * step + evaluate_s + 0.5, "build-s": 0.0, "restore-s": 0.0,
    }  # fmt: skip


# The layout of a full-size run's history on 2026-12-01 (2 local steps): a client's evaluation of
# round r's model rides on round r+1's train message and is recorded under round r's "evaluate";
# only the last round has an evaluate message of its own (with its own handler-s).
HISTORY = {
    "rounds": [
        {"round": 0, "wall-s": 14.5, "server-evaluate": {"eval-s": 14.0}},
        round_record(1, 76.7, 12.5, train(8.2, 0.0), {"eval-s": 13.8}),
        round_record(2, 127.6, 12.6, train(7.0, 13.8), {"eval-s": 12.9}),
        round_record(
            3, 199.6, 14.3, train(7.1, 12.9),
            {"eval-s": 13.2, "handler-s": 13.6, "startup-s": 4.0, "worker-s": 13.3, "build-s": 0.0, "restore-s": 0.0},
        ),
    ]
}  # fmt: skip


def test_an_evaluation_that_rode_on_the_next_train_message_is_not_subtracted_twice():
    round_2 = (127.6 - 76.7) - (2 * 7.0 + 13.8) - 12.6
    round_3 = (199.6 - 127.6) - (2 * 7.1 + 12.9) - 13.2 - 14.3
    assert fixed_costs(HISTORY, steps=2) == pytest.approx([round_2, round_3])


def test_the_middle_rounds_fixed_cost_leaves_out_each_runs_last_round():
    figures = fixed_cost_figures([[2.0, 9.0], [4.0, 11.0]])
    assert figures["fixed-cost-middle-round-s"] == pytest.approx(3.0)
    assert figures["fixed-cost-per-round-s"] == pytest.approx(6.5)
    assert fixed_cost_figures([[5.0]])["fixed-cost-middle-round-s"] is None


def test_the_message_breakdown_has_only_messages_that_were_sent():
    parts = message_breakdown(HISTORY, steps=2)
    assert parts["train"]["evaluation"] == pytest.approx((13.8 + 12.9) / 2)
    assert parts["evaluate"]["evaluation"] == pytest.approx(13.2)
    assert parts["evaluate"]["ClientApp start, message in"] == pytest.approx(4.0)
