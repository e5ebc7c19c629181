"""Success rates with their noise: Wilson intervals on known cases, McNemar's exact test."""

from __future__ import annotations

import pytest

from zk0.rates import compare_text, mcnemar, rate_metrics, rate_text, wilson


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
