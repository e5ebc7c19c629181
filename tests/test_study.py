"""The study's centralised baseline and the study itself (python -m zk0.bench study)."""

from __future__ import annotations

import copy
import json
import math

import pytest
import torch

from zk0.client import build_client
from zk0.policy import build_policy, set_trainable, snapshot
from zk0.training import PooledTrainer


def pooled_over(sessions, run, cameras):
    first = sessions[0]
    bundle = build_policy(run, first.split.meta, first.split.entry, cameras)
    return PooledTrainer.over(bundle, [s.trainer for s in sessions], run)


def test_centralised_training_over_one_client_is_that_clients_own_training(registry, run_config):
    """The pooled loop is the client's loop: same start, data order and noise give the same weights."""
    entry, cameras = registry.clients[0], registry.model_cameras()
    alone = build_client(run_config, entry, cameras)
    pooled = pooled_over([build_client(run_config, entry, cameras)], run_config, cameras)
    start = snapshot(alone.bundle)
    set_trainable(pooled.bundle, start)
    torch.manual_seed(0)
    alone.trainer.fit(3, mu=0.0, global_step=0)
    torch.manual_seed(0)
    pooled.fit(3, mu=0.0, global_step=0)
    mine, theirs = snapshot(alone.bundle), snapshot(pooled.bundle)
    assert any(not torch.equal(mine[n], start[n]) for n in mine), "the steps trained"
    assert all(torch.equal(mine[n], theirs[n]) for n in mine)
    assert pooled.samples_from == {entry.name: 3 * run_config.batch_size}


def test_centralised_training_takes_turns_and_normalises_each_batch_as_its_client_does(registry, run_config):
    cameras = registry.model_cameras()
    sessions = [build_client(run_config, entry, cameras, i) for i, entry in enumerate(registry.clients[:2])]
    pooled = pooled_over(sessions, run_config, cameras)
    pooled._next_batch()  # client 0's turn
    raw = pooled._next_batch()  # client 1's
    assert pooled.dataset_name == sessions[1].split.entry.name
    prepared = pooled._prepare(copy.deepcopy(raw))
    own = sessions[1].trainer._prepare(copy.deepcopy(raw))
    other = sessions[0].trainer._prepare(copy.deepcopy(raw))
    assert set(cameras) <= set(prepared), "client 1's cameras are renamed onto the model's"
    assert torch.equal(prepared["observation.state"], own["observation.state"])
    assert not torch.allclose(prepared["observation.state"], other["observation.state"]), "client 1's statistics"

    pooled.fit(4, mu=0.0, global_step=0)
    batch = run_config.batch_size
    assert pooled.samples_from == {s.split.entry.name: 3 * batch for s in sessions}


@pytest.mark.e2e
def test_study_fills_every_row_and_column_and_evaluates_as_the_federation_does(tmp_path, capsys):
    from zk0.bench.study import main

    argv = ["--settings", "noniid", "--clients", "2", "--rounds", "2", "--local-steps", "2"]
    assert main([*argv, "--output-dir", str(tmp_path), "--batch-size", "4"]) == 0
    out = capsys.readouterr().out
    result = json.loads((tmp_path / "study.json").read_text())["results"]["noniid"]
    matrix = result["matrix"]
    assert list(matrix) == ["start", "FedProx", "FedAvg", "centralised", "local 0", "local 1"]
    for row in matrix.values():
        assert list(row) == ["client 0", "client 1", "server"]
        assert all(math.isfinite(v[k]) and v[k] > 0 for v in row.values() for k in ("action-mse", "policy-loss"))
    clients = ["synth-so100-pickplace-noniid", "synth-so100-stacking-noniid"]
    assert list(result["clients"].values()) == clients
    # all clients' steps in the federation (2 rounds x 2 steps x 2 clients), half from each, batch 4
    assert result["centralised-samples-from"] == {name: 2 * 2 * 4 for name in clients}
    for label in ("FedProx", "FedAvg"):
        own = result["federations"][label]["server-evaluate"]
        assert matrix["start"]["server"]["action-mse"] == pytest.approx(own[0]["action-mse"], rel=1e-6)
        assert matrix[label]["server"]["action-mse"] == pytest.approx(own[-1]["action-mse"], rel=1e-6)
    assert matrix["local 0"] != matrix["local 1"] != matrix["centralised"]
    assert "FedProx / centralised, server action MSE: " in out
    assert "better than every local-only model on the other clients' held-out episodes" in out
    assert (tmp_path / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.e2e
def test_the_sim_setting_judges_every_model_by_success_in_each_clients_conditions(tmp_path, capsys):
    """The simulated setting: the offline matrix as in the others, and each model rolled out in the
    simulator in the server's conditions and each client's own (the start in the server's only)."""
    from zk0.bench.study import main

    argv = ["--settings", "sim", "--clients", "2", "--rounds", "1", "--local-steps", "2", "--batch-size", "2"]
    assert main([*argv, "--demos", "8", "--sim-episodes", "1", "--output-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    result = json.loads((tmp_path / "study.json").read_text())["results"]["sim"]
    assert list(result["clients"].values()) == ["sim-so101-left", "sim-so101-right"]
    assert result["server"] == "sim-so101-eval"
    success = result["success"]
    assert list(success) == ["start", "FedProx", "FedAvg", "centralised", "local 0", "local 1"]
    assert list(success["start"]) == ["server"]
    for label, row in success.items():
        if label != "start":
            assert list(row) == ["client 0", "client 1", "server"]
        for rates in row.values():
            assert 0.0 <= rates["success-rate"] <= rates["lifted-rate"] <= 1.0
            assert 1 <= rates["episode-length"] <= 300
    assert set(result["summary"]["other-clients"]) == {"local 0", "local 1"}
    assert "success in the server's conditions" in out and "closed-loop success" in out
