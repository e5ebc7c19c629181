"""The study's centralised baseline and the study itself (python -m zk0.bench study)."""

from __future__ import annotations

import argparse
import copy
import json
import math
import re

import pytest
import torch

from zk0.data.assets import ensure_dataset
from zk0.data.registry import load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import build_policy, set_trainable, snapshot
from zk0.learning.rates import wilson
from zk0.learning.training import PooledTrainer


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
    [(source, raw)] = pooled._next_batch()  # client 1's
    assert source is sessions[1].trainer and pooled.dataset_name == sessions[1].split.entry.name
    prepared = pooled._prepare([(source, copy.deepcopy(raw))])
    own = sessions[1].trainer._prepare(copy.deepcopy(raw))
    other = sessions[0].trainer._prepare(copy.deepcopy(raw))
    assert set(cameras) <= set(prepared), "client 1's cameras are renamed onto the model's"
    assert torch.equal(prepared["observation.state"], own["observation.state"])
    assert not torch.allclose(prepared["observation.state"], other["observation.state"]), "client 1's statistics"

    pooled.fit(4, mu=0.0, global_step=0)
    batch = run_config.batch_size
    assert pooled.samples_from == {s.split.entry.name: 3 * batch for s in sessions}


def test_a_wide_step_takes_a_batch_from_every_client_each_normalised_as_its_client_does(registry, run_config):
    """The equal-steps baseline: one step, one batch from each client, joined after each client's own
    preprocessing (batch = clients x batch)."""
    cameras = registry.model_cameras()
    sessions = [build_client(run_config, entry, cameras, i) for i, entry in enumerate(registry.clients[:2])]
    first = sessions[0]
    bundle = build_policy(run_config, first.split.meta, first.split.entry, cameras)
    wide = PooledTrainer.over(bundle, [s.trainer for s in sessions], run_config, wide=True)
    drawn = wide._next_batch()
    assert [source for source, _ in drawn] == [s.trainer for s in sessions]
    prepared = wide._prepare([(source, copy.deepcopy(batch)) for source, batch in drawn])
    own = [source._prepare(copy.deepcopy(batch)) for source, batch in drawn]
    batch = run_config.batch_size
    assert len(prepared["action"]) == len(prepared["task"]) == 2 * batch
    assert torch.equal(prepared["observation.state"], torch.cat([o["observation.state"] for o in own]))
    assert not torch.equal(own[0]["observation.state"], sessions[1].trainer._prepare(drawn[0][1])["observation.state"])
    # joined (frames resized, text padded), each sample's loss is what its client's batch alone gives
    cfg, policy = bundle.policy.config, bundle.policy
    noise, time = torch.randn(2 * batch, cfg.chunk_size, cfg.max_action_dim), torch.rand(2 * batch) * 0.9 + 0.05
    with torch.no_grad():
        together = policy.forward(prepared, noise=noise, time=time, reduction="none")[0]
        apart = [
            policy.forward(
                o, noise=noise[i * batch : (i + 1) * batch], time=time[i * batch : (i + 1) * batch], reduction="none"
            )[0]
            for i, o in enumerate(own)
        ]
    assert torch.allclose(together, torch.cat(apart), rtol=1e-4, atol=1e-6)

    wide.fit(2, mu=0.0, global_step=0)
    assert wide.samples_from == {s.split.entry.name: 3 * batch for s in sessions}


@pytest.mark.allowance(240)
@pytest.mark.e2e
def test_study_fills_every_row_and_column_evaluates_as_the_federation_does_and_continues(tmp_path, capsys):
    from zk0.bench.study import main

    argv = ["--settings", "noniid", "--clients", "2", "--rounds", "2", "--local-steps", "2"]
    argv += ["--federations", "FedProx", "--personal-steps", "2"]  # one: each is a whole `flwr run`
    argv += ["--output-dir", str(tmp_path), "--batch-size", "4", "--seeds", "7"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    figures = json.loads((tmp_path / "study.json").read_text())["results"]["noniid"]
    result = figures["seeds"]["7"]
    matrix = result["matrix"]
    assert list(matrix) == ["start", "FedProx", "centralised", "local 0", "local 1", "personal 0", "personal 1",
                            "equal steps"]  # fmt: skip
    assert matrix["personal 0"] != matrix["FedProx"], "each owner's personal model is the federation's fine-tuned"
    for row in matrix.values():
        assert list(row) == ["client 0", "client 1", "server"]
        assert all(math.isfinite(v[k]) and v[k] > 0 for v in row.values() for k in ("action-mse", "policy-loss"))
    assert figures["over-seeds"]["matrix"] == matrix  # the mean of one seed
    clients = ["synth-so100-pickplace-noniid", "synth-so100-stacking-noniid"]
    assert list(result["clients"].values()) == clients
    # all clients' steps in the federation (2 rounds x 2 steps x 2 clients), half from each, batch 4
    assert result["centralised-samples-from"] == {name: 2 * 2 * 4 for name in clients}
    own = result["federations"]["FedProx"]["server-evaluate"]
    assert matrix["start"]["server"]["action-mse"] == pytest.approx(own[0]["action-mse"], rel=1e-6)
    assert matrix["FedProx"]["server"]["action-mse"] == pytest.approx(own[-1]["action-mse"], rel=1e-6)
    assert matrix["local 0"] != matrix["local 1"] != matrix["centralised"] != matrix["equal steps"]
    assert result["summary"]["equal-steps-vs-centralised"] == pytest.approx(
        matrix["equal steps"]["server"]["action-mse"] / matrix["centralised"]["server"]["action-mse"]
    )
    assert "setting noniid, training seed 7: 2 clients" in out
    assert "FedProx / centralised, server action MSE: " in out
    assert "FedProx / equal steps, server action MSE: " in out
    assert "better than every local-only model on the other clients' held-out episodes" in out
    said = [
        line.split(": ", 1)[1].rsplit(" (", 1)[0] for line in out.splitlines() if line.startswith("  noniid, seed 7: ")
    ]
    assert said == [
        "federation FedProx trained",
        "centralised trained",
        "local-only models trained",
        "personal models (FedProx fine-tuned) and local-only models fine-tuned alike",
        "equal steps trained",
        "every model evaluated on every held-out set",
    ]  # progress as it goes
    assert (tmp_path / "study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # Stopped after the federation and some of the models: the same command continues, trains only
    # what is missing (each model from the start of its data order) and ends with the same figures.
    kept = tmp_path / "noniid" / "seed-7"
    federation = sorted(kept.glob("federation-fedprox/*/server/metrics_history.json"))
    assert len(federation) == 1
    written = federation[0].stat().st_mtime_ns
    for name in ("models/local-0.safetensors", "models/local-0-fine-tuned.safetensors", "models/personal-1.safetensors",
                 "offline/local-0.json", "offline/personal-1.json", "offline/equal-steps.json"):  # fmt: skip
        (kept / name).unlink()
    assert main(argv) == 0
    again = json.loads((tmp_path / "study.json").read_text())["results"]["noniid"]["seeds"]["7"]
    assert again["matrix"] == matrix and again["centralised-samples-from"] == result["centralised-samples-from"]
    assert federation[0].stat().st_mtime_ns == written, "the finished federation is not run again"
    capsys.readouterr()
    assert main([*argv[:7], "3", *argv[8:]]) == 2  # other local steps: refused before anything trains
    assert capsys.readouterr().err == (
        f"[zk0] {str(kept)!r} holds models trained with local_steps = 2, not 3: give another --output-dir, "
        "or remove that folder to start over.\n"
    )

    # Its JSON stands in for the seed elsewhere (a folder since lost): nothing trains, the figures stay.
    earlier = tmp_path / "seed-7.json"
    earlier.write_text((tmp_path / "study.json").read_text())
    elsewhere = tmp_path / "elsewhere"
    taken = [*argv[:-6], "--output-dir", str(elsewhere), *argv[-4:], "--seeds-from", str(earlier)]
    assert main(taken) == 0
    assert json.loads((elsewhere / "study.json").read_text())["results"]["noniid"]["seeds"]["7"] == again
    assert not (elsewhere / "noniid").exists(), "nothing was trained"
    capsys.readouterr()
    assert main([*taken[:7], "3", *taken[8:]]) == 2
    assert capsys.readouterr().err == (
        f"[zk0] --seeds-from {str(earlier)!r} was trained with local_steps = 2, not 3; its seeds cannot be "
        "tabled with these.\n"
    )


@pytest.mark.slow
def test_the_sim_setting_rolls_every_model_out_in_each_sets_conditions_and_sums_them_up():
    """The sim setting's closed-loop matrix (the federations that feed it are the other settings'
    code, tested end to end above): every model in the server's conditions and each client's own,
    with that set's processors; the start in the server's only; the targets computed from it."""
    from zk0.bench.study import closed_loop_all, evaluation_sets, rollout_plan, study_run
    from zk0.bench.study_tables import sim_summary

    args = argparse.Namespace(
        rounds=1, local_steps=1, batch_size=2, lr=1e-3, clients=2, model="tiny-128", personal_steps=0, policy="smolvla"
    )
    registry_path = "configs/sim-registry.toml"
    registry = load_registry(registry_path)
    run = study_run(args, registry_path)
    assert run.server_eval_dataset == "sim-so101-eval"
    for entry in registry.entries:
        ensure_dataset(entry.name)
    sessions = [build_client(run, e, registry.model_cameras(), i) for i, e in enumerate(registry.clients[:2])]
    columns = evaluation_sets(sessions, registry, run)
    start = snapshot(sessions[0].bundle)
    labels = ["start", "FedAvg", "centralised", "local 0", "local 1"]  # one federation: each is a rollout per set
    said = []
    success = closed_loop_all(rollout_plan(labels, 2), dict.fromkeys(labels, start), columns, 1, run.seed, said.append)
    assert said == [f"every model rolled out in {column}'s conditions" for column in ("client 0", "client 1", "server")]
    assert list(success) == labels and list(success["start"]) == ["server"]
    for label in labels[1:]:
        assert list(success[label]) == ["client 0", "client 1", "server"]
    for row in success.values():
        for rates in row.values():
            assert 0.0 <= rates["success-rate"] <= rates["lifted-rate"] <= 1.0 and 1 <= rates["episode-length"] <= 300
    # one untrained model everywhere: no federation beats a local-only model, and 0/0 is no ratio
    summary = sim_summary(success, clients=2)
    assert summary["federation-beats-every-local"] == {"FedAvg": False}
    assert set(summary["other-clients"]) == {"local 0", "local 1"}
    if success["centralised"]["server"]["success-rate"] == 0:
        assert summary["vs-centralised"] == {"FedAvg": None}


def test_the_sim_targets_are_printed_from_the_success_matrix_not_the_action_mse(capsys):
    """The sim setting's result holds both summaries; the success lines come from the success one
    (they once read the action-MSE summary, which has the same keys, and printed its ratio)."""
    from zk0.bench.study_tables import print_success, sim_summary
    from zk0.learning.rates import rate_metrics

    def rates(successes: int) -> dict:
        """Ten seeded episodes, the first ``successes`` of them lifted and held."""
        outcomes = [1] * successes + [0] * (10 - successes)
        return {**rate_metrics(outcomes), "lifted-rate": successes / 10, "outcomes": outcomes}

    success = {
        "start": {"server": rates(0)},
        "FedAvg": {"client 0": rates(1), "client 1": rates(3), "server": rates(1)},
        "centralised": {"client 0": rates(2), "client 1": rates(2), "server": rates(4)},
        "local 0": {"client 0": rates(5), "client 1": rates(0), "server": rates(0)},
        "local 1": {"client 0": rates(2), "client 1": rates(6), "server": rates(0)},
        "personal 0": {"client 0": rates(9), "client 1": rates(1), "server": rates(1)},
        "personal 1": {"client 0": rates(1), "client 1": rates(7), "server": rates(1)},
    }
    mse_summary = {"vs-centralised": {"FedAvg": 1.176}, "federation-beats-every-local": {"FedAvg": False}}
    result = {"success": success, "success-summary": sim_summary(success, clients=2), "summary": mse_summary}
    print_success(result)
    out = capsys.readouterr().out
    assert "FedAvg / centralised, success in the server's conditions: 0.25 (target >= 0.9)" in out
    assert "% [95% interval] of 10 seeded episodes" in out and "10 [2, 40]" in out  # FedAvg's 1 of 10
    assert "  FedAvg against local 0 in client 0's conditions: -40 points (within the noise, McNemar p = 0.12)" in out
    assert (
        "  personal 0 against local 0 in client 0's conditions: +40 points (within the noise, McNemar p = 0.12)" in out
    )
    # (90% - 50% + 70% - 60%) / 2 = +25 points; personal 80% on average in their own against centralised 20%
    assert "in the owner's own conditions: +25 points on average (target >= +20); / centralised there: 4.00" in out
    # client 0's model in client 1's conditions: 0% against FedAvg's 30%; client 1's in client 0's: 20% against 10%
    assert "FedAvg succeeds more than every local-only model in the conditions that client never saw: False" in out


def test_over_seeds_every_rate_has_its_mean_spread_and_interval_and_the_targets_theirs(capsys):
    """Two training seeds of ten episodes: the tables give each rate's mean over the seeds, its
    Wilson interval over all twenty episodes and the lowest and highest seed; the targets are
    computed from the paired episodes of both seeds."""
    from zk0.bench.study_tables import over_seeds, print_over_seeds

    def seeded(successes: dict[str, list[int]]) -> list[dict]:
        """Per seed, per model: its successes in each set (the first k of ten episodes succeed)."""
        runs = []
        for seed in (0, 1):
            success = {}
            for name, counts in successes.items():
                label, column = name.split(" | ")
                outcomes = [1] * counts[seed] + [0] * (10 - counts[seed])
                success.setdefault(label, {})[column] = {"outcomes": outcomes}
            matrix = {"FedAvg": {"server": {"action-mse": 2.0 + seed}}}
            runs.append({"seed": seed, "matrix": matrix, "success": success})
        return runs

    counts = {
        "FedAvg | client 0": [4, 2], "FedAvg | server": [3, 3],
        "centralised | client 0": [6, 4], "centralised | server": [6, 6],
        "local 0 | client 0": [2, 4], "local 0 | server": [0, 0],
        "personal 0 | client 0": [9, 7], "personal 0 | server": [1, 1],
    }  # fmt: skip
    result = over_seeds(seeded(counts), clients=1)
    assert result["matrix"] == {"FedAvg": {"server": {"action-mse": 2.5}}}
    personal = result["success"]["personal 0"]["client 0"]
    assert personal["success-rate"] == 0.8 and (personal["seed-min"], personal["seed-max"]) == (0.7, 0.9)
    assert (personal["success-low"], personal["success-high"]) == pytest.approx(wilson(16, 20))
    assert personal["episodes"] == 10 and personal["seeds"] == 2 and personal["per-seed"] == [0.9, 0.7]
    t = result["success-summary"]
    assert t["personal-minus-alone-points"]["value"] == pytest.approx(50.0)  # 80% against 30%
    assert t["personal-minus-alone-points"]["low"] > 20  # 10 of 20 pairs for personal, none against
    assert t["each-owner"]["client 0"] == {"points": pytest.approx(50.0), "mcnemar-p": pytest.approx(2 / 2**10)}
    assert t["personal-vs-centralised-own"]["value"] == pytest.approx(0.8 / 0.5)
    assert t["vs-centralised"]["FedAvg"]["value"] == pytest.approx(0.5)  # 30% against 60%
    assert t["vs-centralised-every-set"]["FedAvg"]["value"] == pytest.approx((0.3 + 0.3) / (0.5 + 0.6))
    assert t["personal-in-server-span"]["value"] == pytest.approx(0.1)
    print_over_seeds("sim-cube", {**result, "seeds": [0, 1]})
    out = capsys.readouterr().out
    assert "mean % over the seeds [95% interval of every seed's 10 episodes] (lowest-highest seed)" in out
    assert "80 [58, 92] (70-90)" in out  # personal 0 in client 0's conditions
    assert "personal models against each owner alone, own conditions: +50 [" in out
    assert "  client 0: +50 points (McNemar p = 0.002 over every seed's pairs)" in out


def test_each_model_is_rolled_out_where_its_figure_is_read():
    """Every model in the server's span; in an owner's own conditions every model but the other
    owners' personal ones and the equal-steps baseline (an offline question); the start only in the server's."""
    from zk0.bench.study import rollout_plan

    labels = ["start", "Nesterov", "centralised", "local 0", "local 1", "personal 0", "personal 1", "equal steps"]
    assert rollout_plan(labels, 2) == {
        "client 0": ["Nesterov", "centralised", "local 0", "local 1", "personal 0"],
        "client 1": ["Nesterov", "centralised", "local 0", "local 1", "personal 1"],
        "server": ["start", "Nesterov", "centralised", "local 0", "local 1", "personal 0", "personal 1"],
    }


def test_the_policy_trains_every_model_and_folders_from_before_the_key_are_smolvlas(tmp_path, capsys):
    """``--policy`` is every model's type, the federations' and the baselines'; a folder or JSON a
    study wrote before the key existed trained SmolVLA, so it continues a SmolVLA study and a
    Diffusion study refuses its seeds in one sentence, before anything trains."""
    from zk0.bench.study import SETTINGS, build_parser, main, study_run, study_stash

    diffusion = build_parser().parse_args(["--policy", "diffusion", "--output-dir", str(tmp_path)])
    assert study_run(diffusion, SETTINGS["sim"]).policy == "diffusion"
    smolvla = build_parser().parse_args(["--output-dir", str(tmp_path)])
    study_stash(smolvla, "mild", 42)
    recorded = json.loads((tmp_path / "mild" / "seed-42" / "settings.json").read_text())
    assert "policy" not in recorded, "as folders were written before --policy"
    earlier = tmp_path / "earlier.json"
    settings = {k: v for k, v in vars(smolvla).items() if k != "policy"} | {"federation_lr": smolvla.lr}  # as main sets it
    earlier.write_text(json.dumps({"settings": settings, "results": {}}))
    assert main(["--output-dir", str(tmp_path / "other"), "--policy", "diffusion", "--seeds-from", str(earlier)]) == 2
    assert capsys.readouterr().err == (
        f"[zk0] --seeds-from {str(earlier)!r} was trained with policy = 'smolvla', not 'diffusion'; its seeds cannot "
        "be tabled with these.\n"
    )


def test_a_multi_task_set_is_tabled_task_by_task_for_each_seed_and_over_the_seeds(capsys):
    """The sim-tasks setting's server set holds two tasks here (five episodes each): each model's
    success in each task with its interval, per seed from that seed's outcomes and over the seeds
    from every seed's; a set of one task gets no such table."""
    from zk0.bench.study import SETTINGS, SIM_SETTINGS
    from zk0.bench.study_tables import over_seeds, print_over_seeds, print_tasks, task_rates

    assert "sim-tasks" in SIM_SETTINGS
    assert load_registry(SETTINGS["sim-tasks"]).server.name == "sim-so101-eval-pick-place-stack-sort-cube"
    kinds = ["place"] * 5 + ["sort"] * 5

    def run(seed: int, place: int, sort: int) -> dict:
        outcomes = [1] * place + [0] * (5 - place) + [1] * sort + [0] * (5 - sort)
        rolled = {"outcomes": outcomes, "kinds": kinds}
        success = {
            "FedAvg": {"client 0": {"outcomes": [1, 0]}, "server": rolled},
            "centralised": {"client 0": {"outcomes": [1, 1]}, "server": {"outcomes": [1] * 10, "kinds": kinds}},
        }
        return {"seed": seed, "matrix": {"FedAvg": {"server": {"action-mse": 1.0}}}, "success": success}

    first = run(0, place=4, sort=1)
    assert task_rates(first["success"]["FedAvg"]["server"])["sort"]["success-rate"] == 0.2
    assert task_rates(first["success"]["FedAvg"]["client 0"]) == {}
    print_tasks(first["success"])
    out = capsys.readouterr().out
    assert "success in each task of server's conditions" in out and "client 0's conditions" not in out
    assert re.search(r"FedAvg\s+80 \[38, 96\]\s+20 \[4, 62\]", out), out
    result = over_seeds([first, run(1, place=2, sort=3)], clients=1)
    tasks = result["success"]["FedAvg"]["server"]["tasks"]
    assert (tasks["place"]["success-rate"], tasks["sort"]["success-rate"], tasks["sort"]["episodes"]) == (0.6, 0.4, 5)
    assert (tasks["sort"]["success-low"], tasks["sort"]["success-high"]) == pytest.approx(wilson(4, 10))
    print_over_seeds("sim-tasks", {**result, "seeds": [0, 1]})
    out = capsys.readouterr().out
    assert re.search(r"centralised\s+100 \[72, 100\]\s+100 \[72, 100\]", out)
    assert "[95% interval of every seed's 5 episodes per task]" in out


def test_a_new_owner_is_rolled_out_in_its_own_conditions_beside_the_global_model_and_tabled(capsys):
    """With --new-owner, its two models are rolled out in its conditions alone, beside the
    federations' model; the paired comparison is printed per seed, and over the seeds with its
    interval and McNemar's p; a name that is not a simulated set-up, or a setting that is not
    simulated, is refused before anything trains."""
    from zk0.bench.models import NEW_ALONE, NEW_FROM_GLOBAL, NEW_OWNER
    from zk0.bench.study import main, rollout_plan
    from zk0.bench.study_tables import EQUAL_STEPS, over_seeds, print_over_seeds, print_success
    from zk0.learning.rates import rate_metrics

    labels = ["start", "Nesterov", "centralised", "local 0", "personal 0", EQUAL_STEPS, NEW_FROM_GLOBAL, NEW_ALONE]
    plan = rollout_plan(labels, clients=1)
    assert plan[NEW_OWNER] == ["Nesterov", NEW_FROM_GLOBAL, NEW_ALONE]
    assert NEW_FROM_GLOBAL not in plan["client 0"] + plan["server"]

    def run(seed: int, fine_tuned: int, alone: int) -> dict:
        def rates(successes: int) -> dict:
            outcomes = [1] * successes + [0] * (10 - successes)
            return {**rate_metrics(outcomes), "lifted-rate": successes / 10, "outcomes": outcomes}

        success = {
            "Nesterov": {"client 0": rates(3), "server": rates(3), NEW_OWNER: rates(0)},
            "centralised": {"client 0": rates(4), "server": rates(4)},
            "local 0": {"client 0": rates(2), "server": rates(1)},
            NEW_FROM_GLOBAL: {NEW_OWNER: rates(fine_tuned)},
            NEW_ALONE: {NEW_OWNER: rates(alone)},
        }
        targets = {"vs-centralised": {}, "federation-beats-every-local": {}}  # (one owner: nobody else's to compare)
        return {"seed": seed, "matrix": {"Nesterov": {"server": {"action-mse": 1.0}}}, "success": success,
                "success-summary": targets, "summary": {}}  # fmt: skip

    first = run(0, fine_tuned=8, alone=2)
    print_success(first)
    out = capsys.readouterr().out
    assert re.search(r"new owner\s*$", out.splitlines()[1]), "the new owner's conditions are a column"
    assert "the new owner: the global model fine-tuned on its demonstrations against trained on them alone: +60 points" in out
    result = over_seeds([first, run(1, fine_tuned=6, alone=2)], clients=1)
    new = result["success-summary"]["new-owner-points"]
    assert new["value"] == pytest.approx(50.0) and new["low"] > 0 and new["mcnemar-p"] < 0.01
    print_over_seeds("sim-tasks", {**result, "seeds": [0, 1]})
    assert "the new owner, fine-tuned from the global model against trained alone: +50 [" in capsys.readouterr().out

    for argv, said in (
        (["--settings", "sim-tasks", "--new-owner", "sim-so101-owner-3-fly"], "--new-owner got 'sim-so101-owner-3-fly'"),
        (["--settings", "mild", "--new-owner", "sim-so101-owner-3-sort-cube"], "and only the simulated settings"),
    ):
        with pytest.raises(SystemExit):
            main(argv)
        assert said in capsys.readouterr().err


@pytest.mark.slow
def test_a_new_owner_trains_from_the_global_model_and_alone_on_its_own_demonstrations(tmp_path):
    """The new owner's two models: each the given steps on its own few demonstrations, one from the
    federation's model and one from the start; kept in a folder of the study's named for the new owner,
    its demonstrations and its steps."""
    from zk0.bench.models import NEW_ALONE, NEW_FROM_GLOBAL, new_owner
    from zk0.bench.stash import Stash
    from zk0.bench.study import study_run

    args = argparse.Namespace(
        rounds=1, local_steps=1, batch_size=2, lr=1e-3, clients=1, model="tiny-128", personal_steps=0,
        policy="smolvla", new_owner="sim-so101-owner-16-sort-cube", new_demos=3, new_steps=2,
    )  # fmt: skip
    registry = load_registry("configs/sim-tasks-registry.toml")
    run = study_run(args, "configs/sim-tasks-registry.toml")
    ensure_dataset(registry.clients[1].name)  # an owner of the federation, for the start it shares
    session = build_client(run, registry.clients[1], registry.model_cameras())
    start = snapshot(session.bundle)
    federated = {name: tensor + 0.01 for name, tensor in start.items()}  # another starting point
    stash = Stash(tmp_path, {})
    newcomer, trained, kept = new_owner(args, run, registry.model_cameras(), 4, federated, start, stash)
    assert newcomer.split.entry.name == "sim-so101-owner-16-sort-cube" and newcomer.split.meta.total_episodes == 3
    assert set(trained) == {NEW_FROM_GLOBAL, NEW_ALONE}
    for label, origin in ((NEW_FROM_GLOBAL, federated), (NEW_ALONE, start)):
        moved = [n for n in origin if not torch.equal(trained[label][n], origin[n])]
        assert moved, f"{label} trained from where it starts"
    assert kept.folder == tmp_path / "new-owner" / "sim-so101-owner-16-sort-cube-3-demos-2-steps"
    assert sorted(p.name for p in (kept.folder / "models").glob("*")) == ["alone.safetensors", "from-global.safetensors"]


def test_a_stopped_federation_continues_from_its_newest_complete_checkpoint(tmp_path, registry):
    """What a study or benchmark passes its federation beside its own keys: a checkpoint every round
    and, once stopped, `resume-from` the newest run of its folder with a complete checkpoint (zk0's
    resume ends as an uninterrupted run: tests/test_federation.py); a run stopped before its first
    checkpoint is removed."""
    from zk0.artifacts.run_folder import save_checkpoint
    from zk0.bench.models import continuation
    from zk0.config import RunConfig
    from zk0.data.loaders import open_metadata

    folder = tmp_path / "federation-nesterov"
    assert continuation(folder) == {"checkpoint-interval": 1}, "a first run starts afresh"
    entry = registry.clients[0]
    bundle = build_policy(RunConfig(device="cpu"), open_metadata(entry), entry, registry.model_cameras())
    for name, rounds in (("2026-12-07_10-00-00", (1, 2)), ("2026-12-07_11-00-00", (1,)), ("2026-12-07_12-00-00", ())):
        (folder / name / "server").mkdir(parents=True)
        for rnd in rounds:
            save_checkpoint(bundle, folder / name, rnd, {})
    assert continuation(folder) == {"checkpoint-interval": 1, "resume-from": str(folder / "2026-12-07_11-00-00")}
    assert sorted(p.name for p in folder.iterdir()) == ["2026-12-07_10-00-00", "2026-12-07_11-00-00"]
