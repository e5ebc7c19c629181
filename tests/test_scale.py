"""Many owners from one registry line, and what they cost (python -m zk0.bench scale)."""

from __future__ import annotations

import json

import pytest

from zk0.bench import scale


@pytest.mark.e2e
def test_a_sixteen_owner_federation_from_one_table_runs_two_rounds_and_is_measured(tmp_path, capsys):
    """The scale benchmark's one federation: 16 synthetic owners from ``[tool.zk0.owners]``, four
    sampled to train each round; start-up, round walls and the processes' memory come back."""
    out = tmp_path / "scale.json"
    argv = ["--owners", "16", "--rounds", "2", "--local-steps", "1", "--output-dir", str(tmp_path), "--json", str(out)]
    assert scale.main(argv) == 0
    row = json.loads(out.read_text())["owners"][0]
    assert (tmp_path / "owners-16" / "owners-16.toml").read_text().count("\n") == 3  # the one table
    assert row["owners"] == 16 and row["trained-per-round"] == [4, 4]
    history = json.loads(next((tmp_path / "owners-16").glob("*/server/metrics_history.json")).read_text())
    owners = {str(i): f"synth-owner-{i}" for i in range(16)}
    assert history["clients"].items() <= owners.items(), "each owner that replied, by its index and dataset"
    trained = {i for r in history["rounds"] for i, c in r["clients"].items() if "train" in c}
    assert 4 <= len(trained) <= 8 and trained <= set(owners)
    assert 0 < row["start-up-s"] < row["flwr-run-s"] and len(row["round-s"]) == 2
    peak = row["peak-mib"]
    assert peak["superlink"] > 0 and peak["simulation"] > 0 and peak["server side"] >= peak["simulation"]
    assert row["client-process-peak-mib"] > 100, "a client process holds torch, lerobot and a SmolVLA"
    assert "steady s" in capsys.readouterr().out


def test_growth_compares_the_largest_federation_with_the_smallest():
    def row(owners, steady, server, client):
        return {
            "owners": owners,
            "steady-round-s": steady,
            "peak-mib": {"server side": server},
            "client-process-peak-mib": client,
        }

    figures = scale.growth([row(4, 2.0, 1000.0, 900.0), row(16, 2.5, 1060.0, 930.0), row(64, 3.0, 1300.0, 960.0)])
    assert figures == {
        "from": 4, "to": 64, "steady-round-ratio": 1.5, "server-mib-per-owner": 5.0, "client-process-mib-per-owner": 1.0,
    }  # fmt: skip
