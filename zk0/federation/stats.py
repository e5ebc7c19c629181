"""Dataset statistics on the wire: lerobot's nested stats dict <-> a flat ``ConfigRecord``.

Statistics are data, not weights: each client normalises with its own, and sends them
alongside its update only so the server can merge them (lerobot's ``aggregate_stats``)
into the global checkpoint (``with_merged_stats``). Keys are ``<feature>|<stat>``; values are flat float lists,
with the array shape under ``<feature>|<stat>|shape``.
"""

from __future__ import annotations

import numpy as np
from flwr.app import ConfigRecord
from lerobot.datasets.compute_stats import aggregate_stats
from lerobot.policies import make_pre_post_processors

from zk0.learning.policy import PolicyBundle

SEP = "|"


def stats_to_record(stats: dict[str, dict]) -> ConfigRecord:
    """Flatten ``{feature: {stat: array}}`` into a ConfigRecord of float lists and shapes."""
    flat: dict[str, list[float] | list[int]] = {}
    for feature, values in stats.items():
        for stat, value in values.items():
            arr = np.asarray(value, dtype=np.float64)
            flat[f"{feature}{SEP}{stat}"] = arr.reshape(-1).tolist()
            flat[f"{feature}{SEP}{stat}{SEP}shape"] = list(arr.shape) or [0]
    return ConfigRecord(flat)


def stats_from_record(record: ConfigRecord) -> dict[str, dict[str, np.ndarray]]:
    """The inverse of ``stats_to_record``."""
    stats: dict[str, dict[str, np.ndarray]] = {}
    for key, value in record.items():
        if key.endswith(f"{SEP}shape"):
            continue
        feature, stat = key.split(SEP)
        shape = [int(s) for s in record[f"{key}{SEP}shape"]]
        stats.setdefault(feature, {})[stat] = np.asarray(value, dtype=np.float64).reshape(shape if shape != [0] else ())
    return stats


def with_merged_stats(bundle: PolicyBundle, stats: list[dict]) -> PolicyBundle:
    """``bundle``'s policy with processors carrying ``stats`` merged (lerobot's ``aggregate_stats``),
    or its own statistics when there are none: what a checkpoint's processors normalise by."""
    merged = aggregate_stats(stats) if stats else bundle.stats
    pre, post = make_pre_post_processors(bundle.policy.config, dataset_stats=merged)
    return PolicyBundle(bundle.policy, pre, post, bundle.trainable_names, bundle.device, merged)
