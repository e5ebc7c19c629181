"""Dataset statistics on the wire: lerobot's nested stats dict <-> a flat ``ConfigRecord``.

Statistics are data, not weights: each client normalises with its own, and sends them
alongside its update only so the server can merge them (lerobot's ``aggregate_stats``)
into the global checkpoint. Keys are ``<feature>|<stat>``; values are flat float lists,
with the array shape under ``<feature>|<stat>|shape``.
"""

from __future__ import annotations

import numpy as np
from flwr.app import ConfigRecord

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
