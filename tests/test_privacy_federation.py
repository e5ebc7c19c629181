"""Differential privacy end to end: the real `flwr run` on a local simulation SuperLink, 2 clients."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import dp_accounting
import pytest

from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.simulation import cpu_federation, flwr_run

pytestmark = pytest.mark.e2e

ONE_ACTOR = cpu_federation(num_supernodes=2, actors=1)
SHORT = "local-steps=2 batch-size=4 eval-batches=1"


def history(run_dir) -> list[dict]:
    return json.loads((run_dir / "server" / "metrics_history.json").read_text())["rounds"]


def rdp_epsilon(noise: float, releases: int) -> float:
    accountant = dp_accounting.rdp.RdpAccountant()
    accountant.compose(dp_accounting.SelfComposedDpEvent(dp_accounting.GaussianDpEvent(noise), releases))
    return accountant.get_epsilon(1e-5)


def test_owner_level_dp_stops_at_its_budget_with_a_checkpoint_and_a_resumed_run_continues_epsilon(flower_env, tmp_path):
    """Noise multiplier 2: two releases spend epsilon 3.19, a third would spend 4.01. With a budget
    of 3.5 the three-round run ends after round 2 in one sentence, exit 0, with round 2's model
    as a checkpoint; the round line, the round's JSON, report.html and each owner's log say the
    epsilon; the owners' normalisation statistics (their min and max among them) never reach the
    server. Resumed with a budget of 5, round 3 brings it to the accountant's 4.01."""
    out = tmp_path / "outputs"
    dp = "dp='owner' dp-noise-multiplier=2.0 dp-clip=0.5 num-server-rounds=3"
    log = flwr_run(flower_env, f"{SHORT} {dp} dp-epsilon-budget=3.5 output-dir='{out}'", ONE_ACTOR)
    (run,) = list(out.iterdir())
    rounds = history(run)
    assert [r["round"] for r in rounds] == [0, 1, 2], log[-3000:]
    assert "Exit Code" not in log
    assert (
        "Round 2 spent epsilon 3.19 at delta 1e-05, and round 3 would take it to 4.01, past dp-epsilon-budget=3.5"
        in log
    )
    assert (run / "models" / "checkpoint_round_2").is_dir()
    assert not list(run.glob("models/*/client_stats/*.json")), "under DP the owners' statistics stay home"
    assert rounds[2]["privacy"]["epsilon"] == pytest.approx(rdp_epsilon(2.0, 2), rel=1e-9)
    assert rounds[2]["privacy"]["releases"] == 2
    assert "epsilon 3.19 of 3.5 (owner-level)" in log
    assert "Owner-level differential privacy" in (run / "report.html").read_text()
    client_log = (run / "clients" / "client_0" / "client.log").read_text()
    assert "the models released before round 2 have spent epsilon 2.166 at delta 1e-05" in client_log
    assert all(c["train"]["update-norm"] > 0 for c in rounds[1]["clients"].values())

    log = flwr_run(flower_env, f"{SHORT} {dp} dp-epsilon-budget=5.0 output-dir='{out}' resume-from='{run}'", ONE_ACTOR)
    rounds = history(run)
    assert [r["round"] for r in rounds] == [0, 1, 2, 3], log[-3000:]
    assert rounds[3]["privacy"]["releases"] == 3
    assert rounds[3]["privacy"]["epsilon"] == pytest.approx(rdp_epsilon(2.0, 3), rel=1e-9)


def test_record_level_dp_says_each_owners_epsilon(flower_env, tmp_path):
    """Each owner trains with DP-SGD; its epsilon is in its reply, the round line, the JSON, the
    report and its own log, and the run trains (the global model moves)."""
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"{SHORT} dp='record' num-server-rounds=2 output-dir='{out}'", ONE_ACTOR)
    (run,) = list(out.iterdir())
    rounds = history(run)
    assert [r["round"] for r in rounds] == [0, 1, 2], log[-3000:]
    spent = [c["train"]["record-epsilon"] for c in rounds[2]["clients"].values()]
    assert len(spent) == 2 and all(0 < e <= 8.0 for e in spent)
    assert f"epsilon up to {max(spent):.3g} of 8 (each owner's demonstrations)" in log
    assert "Record-level differential privacy" in (run / "report.html").read_text()
    client_log = (run / "clients" / "client_1" / "client.log").read_text()
    assert "Privacy spent by synth-so100-stacking's demonstrations: epsilon" in client_log


def with_public_set(path: Path, public: str) -> Path:
    """The project's registry with its client set ``public`` made public (the server's to train on)."""
    tables = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["zk0"]["datasets"]
    lines = []
    for name, table in tables.items():
        role = "public" if name == public else table.get("role", "client")
        cameras = ", ".join(f'{source} = "{target}"' for source, target in table["cameras"].items())
        lines += [f"[tool.zk0.datasets.{name}]", f'repo_id = "{table["repo_id"]}"', "synthetic = true"]
        lines += [f'role = "{role}"', f"cameras = {{ {cameras} }}", ""]
    path.write_text("\n".join(lines))
    return path


def test_the_trusted_direction_leaves_a_hostile_owner_out_through_flwr_run(flower_env, tmp_path):
    """Three owners of the project's synthetic sets, the third hostile (``python -m zk0.bench
    privacy``'s attacker: its update replaced at the server by ByzFL's sign flipping of the two
    honest ones, which passes update-clip), and the fourth set public: with ``aggregation =
    "monna"`` the server trains on the public set each round and leaves out the update farthest
    from its own, the hostile one, naming it; the global model still learns."""
    from zk0.bench.attacks import attacked_app

    registry = with_public_set(tmp_path / "registry.toml", "synth-so101-reach")
    out = tmp_path / "outputs"
    app = attacked_app(tmp_path / "app", "sign-flipping", [2])
    config = (
        f"registry='{registry}' num-server-rounds=2 local-steps=20 batch-size=8 lr=2e-3 eval-batches=1000 "
        "eval-frequency=2 aggregation='monna' hostile-owners=1 min-train-clients=3"
    )
    log = flwr_run(flower_env, f"{config} output-dir='{out}'", cpu_federation(num_supernodes=3, actors=1), app=app)
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    rounds = history(runs[0])
    assert [r["round"] for r in rounds] == [0, 1, 2], log[-3000:]
    server_log = (runs[0] / "server" / "server.log").read_text()
    assert "aggregation monna (ByzFL, hostile-owners=1)" in server_log
    assert "Trusted direction: 20 local steps a round on ['synth-so101-reach']" in server_log
    for r in (1, 2):
        assert (
            f"Round {r}: the benchmark's attacker replaced the updates of client(s) [2] with ByzFL's sign" in server_log
        )
        assert f"Round {r}: left out the update(s) of client(s) [2], farthest from the server's own" in server_log
        assert rounds[r]["clients"]["2"]["train"]["update-scale"] == 1.0, "the hostile update passes update-clip"
    mse = [r["server-evaluate"]["action-mse"] for r in rounds if "server-evaluate" in r]
    assert mse[-1] < 0.8 * mse[0], f"it learns as the honest owners' mean would: {mse}"
