"""A success rate is a measurement with noise: its interval, and whether two models differ.

Closed-loop success is *k* successes in *n* seeded episodes. With 20 episodes a rate near 50%
has a standard error of about 11 points, so every rate zk0 prints or writes carries *n* and a
95% Wilson score interval (which, unlike the normal approximation, stays inside [0, 1] and is
not [0, 0] at 0/n). Two models rolled out on the same seeded episodes are compared pairwise:
McNemar's exact test looks only at the episodes where they disagree. A figure over several training
seeds (a mean, a difference, a ratio) gets a bootstrap interval over the episodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from zk0.sim.tasks import KINDS

Z95 = 1.959963984540054  # the standard normal's 97.5th percentile


def wilson(successes: int, episodes: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of ``successes`` out of ``episodes`` (95% by default)."""
    if episodes <= 0:
        return 0.0, 1.0
    p = successes / episodes
    denominator = 1 + z * z / episodes
    centre = (p + z * z / (2 * episodes)) / denominator
    half = z * math.sqrt(p * (1 - p) / episodes + z * z / (4 * episodes * episodes)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


def rate_metrics(outcomes: Sequence[bool], prefix: str = "success") -> dict[str, float]:
    """``{prefix}-rate``, its 95% interval (``-low``, ``-high``) and the episode count."""
    n, k = len(outcomes), int(sum(bool(o) for o in outcomes))
    low, high = wilson(k, n)
    return {f"{prefix}-rate": k / n if n else 0.0, f"{prefix}-low": low, f"{prefix}-high": high, "episodes": float(n)}


def rate_text(rate: float, episodes: int) -> str:
    """``45% [36, 55] of 100``: a rate as people read it, with its interval and episode count."""
    k = round(rate * episodes)
    low, high = wilson(k, episodes)
    return f"{100 * rate:.0f}% [{100 * low:.0f}, {100 * high:.0f}] of {episodes}"


def success_text(metrics: dict, prefix: str = "") -> str:
    """``45% [36, 55] of 100`` from a closed-loop evaluation's metrics (``prefix``: a client's
    ``own-`` or ``personal-own-`` ones), without the interval for a record from before zk0 kept the
    episode count."""
    episodes = int(metrics.get(f"{prefix}episodes", 0))
    rate = float(metrics[f"{prefix}success-rate"])
    return rate_text(rate, episodes) if episodes else f"{100 * rate:.0f}%"


def per_task(metrics: dict, prefix: str = "") -> dict[str, dict]:
    """Each task's figures in a multi-task closed-loop evaluation's metrics (``place-success-rate``
    -> ``{"place": {"success-rate": ...}}``), in the order of ``KINDS``; empty for a single task."""
    return {
        kind: {
            key.removeprefix(f"{prefix}{kind}-"): value
            for key, value in metrics.items()
            if key.startswith(f"{prefix}{kind}-")
        }
        for kind in KINDS
        if f"{prefix}{kind}-success-rate" in metrics
    }


def simulator_text(metrics: dict) -> str:
    """``success 45% [36, 55] of 100 in the simulator``, and in a multi-task evaluation the task it
    does worst: what a console line says of a closed-loop evaluation (nothing without one)."""
    if "success-rate" not in metrics:
        return ""
    text = f"success {success_text(metrics)} in the simulator"
    if tasks := per_task(metrics):
        kind, worst = min(tasks.items(), key=lambda task: task[1]["success-rate"])
        text += f" over {len(tasks)} tasks (worst: {kind}, {success_text(worst)})"
    return text


def mcnemar(first: Sequence[bool], second: Sequence[bool]) -> float:
    """Two-sided exact McNemar p-value for two models' outcomes on the same episodes, in order.

    Only discordant episodes count (one model succeeded, the other not); under "no difference"
    each is as likely to go either way, so the p-value is a binomial(discordant, 1/2) tail.
    """
    if len(first) != len(second):
        raise ValueError(f"McNemar's test needs the same episodes: got {len(first)} and {len(second)} outcomes.")
    only_first = sum(1 for a, b in zip(first, second, strict=True) if a and not b)
    only_second = sum(1 for a, b in zip(first, second, strict=True) if b and not a)
    discordant = only_first + only_second
    if discordant == 0:
        return 1.0
    tail = sum(math.comb(discordant, i) for i in range(min(only_first, only_second) + 1)) / 2**discordant
    return min(1.0, 2 * tail)


def compare_text(first: Sequence[bool], second: Sequence[bool]) -> str:
    """How two models on the same episodes differ: the difference in points and whether it is
    beyond the noise (McNemar, 5%)."""
    difference = 100 * (sum(map(bool, first)) - sum(map(bool, second))) / max(1, len(first))
    p = mcnemar(first, second)
    verdict = "beyond the noise" if p < 0.05 else "within the noise"
    return f"{difference:+.0f} points ({verdict}, McNemar p = {p:.2g})"


def model_choice(metrics: dict) -> str:
    """Which of an owner's two models to run, by their success in the owner's own conditions on the
    same seeded episodes (``own-*``, ``personal-own-*`` and McNemar's ``personal-own-p``), never by
    held-out MSE: the one that succeeds more often where the difference is beyond the noise, else
    the global model, which the federation goes on improving. Empty without both rollouts."""
    p = metrics.get("personal-own-p")
    if p is None:
        return ""
    if p < 0.05:
        better = "personal" if metrics["personal-own-success-rate"] > metrics["own-success-rate"] else "global"
        return f"run the {better} model (McNemar p {p:.2g})"
    return f"run the global model (no difference beyond the noise, McNemar p {p:.2g})"


def bootstrap(
    outcomes: dict[str, Sequence[Sequence[int]]],
    statistic: Callable[[dict[str, np.ndarray]], np.ndarray],
    draws: int = 2000,
    seed: int = 0,
) -> tuple[float, float]:
    """The 95% percentile interval of ``statistic`` over episodes drawn again with replacement.

    ``outcomes`` maps a name (a model in a set of conditions) to one row of per-episode outcomes
    per training seed. Each draw takes one set of episode indices per row and per number of
    episodes, and uses it for every name with that many, so models rolled out on the same episodes
    stay paired (sets of conditions, whose episodes are independent, are drawn jointly where they
    have as many, which is as valid; a multi-task set has more episodes than a one-task set).
    ``statistic`` maps name -> array ``[..., seeds, episodes]`` to ``[...]``, as numpy does: it is
    called once, on every draw together. The interval is the episodes' noise; how much training
    seeds differ is the spread between rows, reported beside it.
    """
    arrays = {name: np.asarray(rows, dtype=float) for name, rows in outcomes.items()}
    seeds = next(iter(arrays.values())).shape[0]
    rng = np.random.default_rng(seed)
    lengths = sorted({a.shape[1] for a in arrays.values()})
    index = {n: rng.integers(0, n, size=(draws, seeds, n)) for n in lengths}
    rows = np.arange(seeds)[None, :, None]
    with np.errstate(divide="ignore", invalid="ignore"):  # a ratio over a draw with no success is no figure
        drawn = {name: a[rows, index[a.shape[1]]] for name, a in arrays.items()}
        values = np.asarray(statistic(drawn), dtype=float)
    values = values[np.isfinite(values)]
    if not values.size:
        return math.nan, math.nan
    low, high = np.quantile(values, [0.025, 0.975])
    return float(low), float(high)
