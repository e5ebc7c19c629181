"""One owner's update as the server checks and bounds it, before any rule combines updates.

What every reply must share with the global model (names, shapes, dtypes, finite values), how far
it moves the model, the same move scaled (update-clip, FedNova's normalisation), and the local
steps it took. Pure functions of the arrays, so the strategy (zk0.federation.aggregation), the
benchmarks and the tests read an update the same way.
"""

from __future__ import annotations

import numpy as np
from flwr.app import Array, ArrayRecord, Message


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


def update_norm(update: ArrayRecord, current: dict[str, np.ndarray]) -> float:
    """How far an update moves the global model (``current``, decoded once per round): the L2 norm
    of the difference, over every array."""
    total = sum(np.sum(np.square(update[n].numpy() - start), dtype=np.float64) for n, start in current.items())
    return float(np.sqrt(total))


def scaled_update(update: ArrayRecord, current: dict[str, np.ndarray], scale: float) -> ArrayRecord:
    """``update`` with its change to the global model (``current``, decoded) multiplied by ``scale``."""
    moved = {}
    for name, start in current.items():
        moved[name] = Array(np.asarray(start + scale * (update[name].numpy() - start), dtype=start.dtype))
    return ArrayRecord(moved)


def steps_taken(msg: Message) -> int:
    """The local steps a train reply's update took (``local-steps`` in its metrics)."""
    (metrics,) = msg.content.metric_records.values()
    return int(metrics["local-steps"])
