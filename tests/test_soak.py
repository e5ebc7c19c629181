"""The soak benchmark's arithmetic on the rows its watch writes at each round's end (zk0.bench.soak)."""

from __future__ import annotations

import pytest

from zk0.bench.soak import growth


def row(number: int, server: float, clients: dict[str, float], fds: int, size: int) -> dict:
    return {
        "round": number, "s": 3.0 * number, "mib": {"server side": server}, "client-processes-mib": clients,
        "server-fds": fds, "server-threads": 40, "client-fds": 2 * fds, "client-threads": 60, "output-bytes": size,
    }  # fmt: skip


def test_growth_runs_from_the_first_round_at_or_after_the_start_to_the_last():
    rows = [
        row(5, 900.0, {"11": 700.0}, 30, 10),
        row(10, 1000.0, {"11": 800.0, "12": 790.0}, 31, 50),
        row(200, 1030.0, {"11": 840.0, "12": 790.0, "13": 500.0}, 31, 80),
    ]
    g = growth(rows, start=8)
    assert g["from-round"] == 10 and g["to-round"] == 200
    assert g["server-side-memory"] == pytest.approx(0.03)
    assert g["client-process-memory"] == pytest.approx({"11": 0.05, "12": 0.0})  # a process seen at both ends
    assert (g["server-fds"], g["client-fds"], g["server-threads"], g["output-bytes"]) == (0, 0, 0, 30)
