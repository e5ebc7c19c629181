"""Success rates with their noise: Wilson intervals on known cases, McNemar's exact test, the bootstrap."""

from __future__ import annotations

import math

import pytest

from zk0.learning.rates import bootstrap, compare_text, mcnemar, rate_metrics, rate_text, wilson


@pytest.mark.parametrize(
    ("successes", "episodes", "low", "high"),
    [
        (0, 20, 0.0, 0.1611),
        (10, 20, 0.2993, 0.7007),
        (20, 20, 0.8389, 1.0),
        (45, 100, 0.3561, 0.5476),
        (1, 1, 0.2065, 1.0),
    ],
)
def test_wilson_intervals_of_known_cases(successes, episodes, low, high):
    got = wilson(successes, episodes)
    assert got == pytest.approx((low, high), abs=5e-5)
    assert got[0] <= successes / episodes <= got[1]


def test_a_rate_carries_its_interval_and_episode_count():
    metrics = rate_metrics([True] * 9 + [False] * 11)
    assert metrics["success-rate"] == 0.45 and metrics["episodes"] == 20
    assert (metrics["success-low"], metrics["success-high"]) == pytest.approx(wilson(9, 20))
    assert rate_text(0.45, 100) == "45% [36, 55] of 100"
    assert rate_text(0.0, 20) == "0% [0, 16] of 20", "0/20 is not [0, 0]"


def test_mcnemar_counts_only_the_episodes_where_the_models_disagree():
    same = [True, False] * 10
    assert mcnemar(same, same) == 1.0
    better = [True] * 6 + [False] * 14
    worse = [False] * 20
    assert mcnemar(better, worse) == pytest.approx(2 / 2**6)  # 6 discordant, all one way
    assert mcnemar(worse, better) == mcnemar(better, worse)
    # 7 against 3 discordant of 10: p = 2 * P(X <= 3 | 10, 1/2) = 0.34375
    first = [True] * 7 + [False] * 3 + [True] * 5
    second = [False] * 7 + [True] * 3 + [True] * 5
    assert mcnemar(first, second) == pytest.approx(0.34375)
    assert compare_text(better, worse) == "+30 points (beyond the noise, McNemar p = 0.031)"
    assert compare_text(first, second).startswith("+27 points (within the noise")
    with pytest.raises(ValueError, match="the same episodes: got 2 and 3"):
        mcnemar([True, False], [True, False, True])


def mean_rate(name: str):
    return lambda v: v[name].mean(axis=(-2, -1))


def test_the_bootstrap_keeps_pairs_and_gives_the_normal_interval_where_it_applies():
    """Two models on the same 100 episodes, disagreeing on 20 (a: +20 of them): the paired
    difference's standard error is sqrt(0.2 * 0.8 / 100) = 0.04, so about +-0.078 around +0.2; an
    unpaired bootstrap would be twice as wide."""
    outcomes = {"a": [[1] * 50 + [0] * 50], "b": [[1] * 30 + [0] * 70]}
    low, high = bootstrap(outcomes, lambda v: (v["a"] - v["b"]).mean(axis=(-2, -1)))
    assert low == pytest.approx(0.2 - 0.078, abs=0.02) and high == pytest.approx(0.2 + 0.078, abs=0.02)
    assert bootstrap(outcomes, mean_rate("a")) == pytest.approx(wilson(50, 100), abs=0.02)
    # the same model against itself: no difference in any draw
    assert bootstrap({"a": outcomes["a"]}, lambda v: (v["a"] - v["a"]).mean(axis=(-2, -1))) == (0.0, 0.0)


def test_the_bootstrap_draws_within_each_seed_and_says_when_a_ratio_has_no_figure():
    """Three training seeds of 10 episodes: each seed's row is drawn from its own episodes, so a
    seed that always succeeds stays at 100% and the mean over seeds moves only by the others."""
    rows = [[1] * 10, [0] * 10, [1] * 5 + [0] * 5]
    low, high = bootstrap({"a": rows}, mean_rate("a"))
    assert 1 / 3 < low <= 0.5 <= high < 2 / 3  # the first two seeds never move: (1 + 0 + [0, 1]) / 3
    ratio = bootstrap(
        {"a": rows, "zero": [[0] * 10] * 3}, lambda v: v["a"].mean(axis=(-2, -1)) / v["zero"].mean(axis=(-2, -1))
    )
    assert all(math.isnan(x) for x in ratio)


def test_the_bootstrap_draws_sets_of_different_sizes_each_paired_within_itself():
    """A multi-task set's rollouts have more episodes than a one-task owner's: each size gets draws of
    its own, and two models on the same episodes stay paired (their difference never moves)."""
    one_task = [[1, 0] * 5]
    every_task = [[1, 1, 0, 0] * 10]
    outcomes = {"a | owner": one_task, "b | owner": one_task, "a | server": every_task, "b | server": every_task}
    assert bootstrap(outcomes, lambda v: v["a | owner"].mean(axis=(-2, -1)) - v["b | owner"].mean(axis=(-2, -1))) == (0.0, 0.0)
    low, high = bootstrap(outcomes, lambda v: v["a | server"].mean(axis=(-2, -1)) - v["a | owner"].mean(axis=(-2, -1)))
    assert low < 0.0 < high
