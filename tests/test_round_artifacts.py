"""The server's one progress line per round, from what the round recorded."""

from __future__ import annotations

from types import SimpleNamespace

from zk0 import round_artifacts
from zk0.artifacts import History
from zk0.config import RunConfig
from zk0.round_artifacts import RoundArtifacts


def test_each_round_ends_with_a_line_a_person_reads(tmp_path, monkeypatch):
    clock = iter([100.0, 130.0, 170.0])  # started, then the ends of rounds 1 and 2
    monkeypatch.setattr(round_artifacts, "time", SimpleNamespace(perf_counter=lambda: next(clock)))
    history = History(tmp_path, {0: "a", 1: "b", 2: "c"}, {})
    artifacts = RoundArtifacts(RunConfig(num_server_rounds=4), None, None, None, history, None, {}, first_round=1)
    history.add_client(1, "train", 0, {"train-loss": 0.4})
    history.add_client(1, "train", 1, {"train-loss": 0.6})
    history.add_client(1, "train", 2, {"error": "Client 2 (c): Dataset 'c' records no camera."})
    history.add(1, "aggregate-train", {"train-loss": 0.5})
    history.add(1, "server-evaluate", {"action-mse": 61.54321})
    history.add_client(2, "train", 0, {"train-loss": 0.3})
    assert artifacts.progress(1) == (
        "Round 1/4: 2 clients trained, train loss 0.5, server action MSE 61.54, 30.0 s/round, about 1m 30s left"
    )
    assert artifacts.progress(2) == (
        "Round 2/4: 1 client trained, train loss -, server action MSE not evaluated, 35.0 s/round, about 1m 10s left"
    )
