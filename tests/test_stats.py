"""Dataset statistics survive the trip through a ConfigRecord and merge with lerobot's aggregation."""

from __future__ import annotations

import numpy as np
from lerobot.datasets.compute_stats import aggregate_stats

from zk0.data.loaders import open_metadata
from zk0.federation.stats import stats_from_record, stats_to_record


def test_stats_round_trip_and_merge(registry):
    stats = [open_metadata(e).stats for e in registry.clients[:2]]
    decoded = [stats_from_record(stats_to_record(s)) for s in stats]
    for original, back in zip(stats, decoded, strict=True):
        assert set(original) == set(back)
        for feature in original:
            for key, value in original[feature].items():
                np.testing.assert_allclose(back[feature][key], np.asarray(value), rtol=1e-6)
    merged = aggregate_stats([{k: v for k, v in s.items() if k in ("observation.state", "action")} for s in decoded])
    counts = [s["action"]["count"] for s in decoded]
    assert merged["action"]["count"] == sum(counts)
    assert (
        merged["action"]["min"].tolist()
        == np.minimum(decoded[0]["action"]["min"], decoded[1]["action"]["min"]).tolist()
    )
