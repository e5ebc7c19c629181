"""End to end: the real `flwr run` against a local simulation SuperLink, offline, 2 clients."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import batch_to_transition, transition_to_batch
from safetensors.torch import load_file

from zk0.bench.robust import scaled_client_app
from zk0.config import RunConfig
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry
from zk0.deployment.simulation import cpu_federation, flwr_run
from zk0.learning.policy import build_policy, get_trainable

pytestmark = pytest.mark.e2e

# Two clients served by one Ray actor: which actor runs a node's message is up to Ray, so one
# actor makes "each client builds its policy once per run" exact.
ONE_ACTOR = cpu_federation(num_supernodes=2, actors=1)


# Three short rounds, a checkpoint after each, bf16 on the wire (the default): every artifact is
# checked on this run, the resume test continues it from round 2, and the bf16 test compares it with
# the same run in fp32 (each `flwr run` costs half a minute of fixed start-up on 2 cores). Steps and
# learning rate enough for the server's action MSE, over all its held-out batches, to fall by a fifth.
STEPS, BATCH = 15, 4
THREE_ROUNDS = (
    f"num-server-rounds=3 local-steps={STEPS} batch-size={BATCH} lr=2e-3 checkpoint-interval=1 eval-batches=1000"
    " hf-repo-id='zk0-tests/federated-smolvla' personal-steps=4"
)


@pytest.fixture(scope="module")
def three_rounds(flower_env, tmp_path_factory) -> tuple[Path, str]:
    """The run folder of one ``THREE_ROUNDS`` federation, and what `flwr run` printed."""
    out = tmp_path_factory.mktemp("three-rounds")
    log = flwr_run(flower_env, f"{THREE_ROUNDS} output-dir='{out}'", ONE_ACTOR)
    runs = list(out.iterdir())
    assert len(runs) == 1, log[-3000:]
    return runs[0], log


def test_two_clients_three_rounds_write_every_artifact(three_rounds):
    run, log = three_rounds
    server = run / "server"
    for name in [
        "server.log",
        "metrics_history.json",
        "policy_loss.png",
        "action_mse.png",
        "round_0.json",
        "round_1.json",
        "round_2.json",
        "round_3.json",
    ]:
        assert (server / name).stat().st_size > 0, name
    history = json.loads((server / "metrics_history.json").read_text())
    assert history["clients"] == {"0": "synth-so100-pickplace", "1": "synth-so100-stacking"}
    assert [r["round"] for r in history["rounds"]] == [0, 1, 2, 3]
    last = history["rounds"][-1]
    assert set(last["clients"]) == {"0", "1"}, "clients are named by their short index, not node ids"
    for index, client in last["clients"].items():
        assert client["dataset"] == history["clients"][index]
        assert client["train"]["num-examples"] == STEPS * BATCH
        assert {"train-loss", "proximal-loss", "grad-norm", "step-time", "peak-gpu-gib", "host-rss-gib"} <= set(
            client["train"]
        )
        assert {"policy-loss", "action-mse"} <= set(client["evaluate"])
        # bf16 on the wire (the default): about half the fp32 bytes of the trainable weights
        assert 0.45 < client["train"]["update-bytes"] / last["global-arrays"]["bytes"] < 0.55
        client_dir = run / "clients" / f"client_{index}"
        client_log = (client_dir / "client.log").read_text()
        assert "Round 3 train" in client_log and "Round 3 evaluate" in client_log
        assert client_log.count("built SmolVLA") == 1, "policy and dataset are kept across rounds"
        assert json.loads((client_dir / "round_3.json").read_text())["train"]["num-examples"] == STEPS * BATCH
        # its personal model: judged beside the global one, kept on its machine as a policy lerobot loads
        assert {"personal-action-mse", "personal-policy-loss", "personal-train-loss"} <= set(client["evaluate"])
        personal = client_dir / "models" / "personal"
        assert json.loads((personal / "zk0_round.json").read_text())["round"] == 3
        assert SmolVLAPolicy.from_pretrained(personal).config.chunk_size == 10
        said = (
            f"client {index} {client['evaluate']['action-mse']:.4g} -> {client['evaluate']['personal-action-mse']:.4g}"
        )
        assert said in log.split("Personal models after round 3 (held-out action MSE, global -> personal): ")[-1]
    report = (run / "report.html").read_text()
    assert 'id="personal"' in report and "--policy.path=clients/client_&lt;i&gt;/models/personal" in report
    assert {"policy-loss", "action-mse"} <= set(last["server-evaluate"])
    assert {"policy-loss", "action-mse"} <= set(last["aggregate-evaluate"])
    models = run / "models"
    # a checkpoint every round, the newest two kept (keep-checkpoints' default): round 1's is gone
    assert sorted(p.name for p in models.iterdir()) == ["best", "checkpoint_round_2", "checkpoint_round_3"]
    best = last["best"]
    assert best["action-mse"] == min(r["server-evaluate"]["action-mse"] for r in history["rounds"])
    said = "no round beat the starting model" if best["round"] == 0 else f"models/best is round {best['round']}"
    assert said in log.split("Done in ")[-1]

    checkpoint = models / "checkpoint_round_3"
    policy = SmolVLAPolicy.from_pretrained(checkpoint)
    trainable = [n for n, p in policy.named_parameters() if p.requires_grad]
    assert last["global-arrays"]["tensors"] == len(trainable) < len(list(policy.parameters()))
    payload = 4 * sum(p.numel() for p in policy.parameters() if p.requires_grad)  # fp32 trainable weights
    assert payload <= last["global-arrays"]["bytes"] < 1.05 * payload

    preprocessor = PolicyProcessorPipeline.from_pretrained(
        checkpoint, "policy_preprocessor.json", to_transition=batch_to_transition, to_output=transition_to_batch
    )
    dataset = LeRobotDataset(
        "zk0/synth_so100_stacking", root=Path(os.environ["ZK0_CACHE"]) / "datasets/zk0/synth_so100_stacking"
    )
    frame = dataset[0]
    observation = {
        "observation.images.camera1": frame["observation.images.laptop"],
        "observation.images.camera2": frame["observation.images.phone"],
        "observation.state": frame["observation.state"],
        "task": frame["task"],
    }
    chunk = policy.predict_action_chunk(preprocessor(observation))
    assert chunk.shape == (1, policy.config.chunk_size, 6)
    assert torch.isfinite(chunk).all()

    # Each client's own statistics travel with the checkpoint; the processors carry the merged ones.
    assert sorted(p.name for p in (checkpoint / "client_stats").iterdir()) == [
        "client_0_synth-so100-pickplace.json",
        "client_1_synth-so100-stacking.json",
    ]

    # Without HF_TOKEN the Hub folder is staged (a loadable lerobot model dir with its card), not pushed.
    assert log.count("hf-repo-id is set but HF_TOKEN is not") == 1
    staged = run / "hub" / f"best_round_{best['round']}"  # the run's best model goes to the Hub
    assert SmolVLAPolicy.from_pretrained(staged).config.chunk_size == policy.config.chunk_size
    card = (staged / "README.md").read_text()
    for repo_id in ["zk0/synth_so100_pickplace", "zk0/synth_so100_stacking", "zk0/synth_so100_eval"]:
        assert repo_id in card
    assert "--policy.path=zk0-tests/federated-smolvla" in card
    defaults = "| server optimiser | nesterov (server-lr 1.0, momentum 0.5) |"
    assert defaults in card, "the defaults, as the card says them"
    assert (staged / "policy_loss.png").is_file()

    # The same checkpoint is a valid starting point for a new federation (`model=<dir>`).
    registry = load_registry()
    entry = registry.clients[1]
    resumed = build_policy(RunConfig(model=str(checkpoint)), open_metadata(entry), entry, registry.model_cameras())
    start = get_trainable(resumed)
    assert set(start) == set(trainable)
    saved = policy.state_dict()
    for name in trainable:
        assert (start[name].numpy() == saved[name].numpy()).all(), name


def test_a_resumed_run_ends_with_the_same_model_as_an_uninterrupted_one(flower_env, three_rounds, tmp_path):
    """The server optimiser's state (outer Nesterov's momentum, the default) comes back from the
    checkpoint, and each client's optimizer moments and data position from the state it kept at that
    round: resumed after round 2, the run's round-3 model equals the uninterrupted run's, bit for bit.
    (Client 1's 120 training frames are 30 batches: its epoch ends with round 2, where a resumed
    client once drew other noise than the uninterrupted one.)"""
    straight, log = three_rounds
    assert (straight / "models" / "checkpoint_round_3").is_dir(), log[-3000:]
    resumed_out = tmp_path / "resumed"
    # What an interruption after round 2's checkpoint leaves: the folder without round 3's checkpoint
    # and the clients' round-3 state (round 3's other files are rewritten by the resumed run).
    interrupted = resumed_out / straight.name
    shutil.copytree(straight, interrupted)
    shutil.rmtree(interrupted / "models" / "checkpoint_round_3")
    for state in interrupted.glob("clients/*/trainer_state/round_3.safetensors"):
        state.unlink()
    assert len(list(interrupted.glob("clients/*/trainer_state/round_2.safetensors"))) == 2
    assert (interrupted / "models" / "checkpoint_round_2" / "server_optimiser.safetensors").is_file()

    config = f"{THREE_ROUNDS} output-dir='{resumed_out}' resume-from='{interrupted}'"
    log = flwr_run(flower_env, config, ONE_ACTOR)
    assert (interrupted / "models" / "checkpoint_round_3").is_dir(), log[-3000:]
    expected = load_file(straight / "models" / "checkpoint_round_3" / "model.safetensors")
    resumed = load_file(interrupted / "models" / "checkpoint_round_3" / "model.safetensors")
    assert set(resumed) == set(expected)
    differ = [name for name in expected if not torch.equal(resumed[name], expected[name])]
    assert not differ, f"{len(differ)} tensors differ, e.g. {differ[:3]}"
    for client in ("client_0", "client_1"):
        said = (interrupted / "clients" / client / "client.log").read_text()
        assert f"Continuing at batch {2 * STEPS} with the optimizer state this client kept after round 2." in said
        # the personal model is fine-tuned again from the same global model, data and seed: the same one
        personal = [load_file(run / "clients" / client / "models" / "personal" / "model.safetensors")
                    for run in (straight, interrupted)]  # fmt: skip
        assert all(torch.equal(personal[0][name], personal[1][name]) for name in personal[0]), client


def test_a_run_that_only_gets_worse_hands_back_round_0(flower_env, tmp_path, registry):
    """lr = 1 wrecks the model in round 1; models/best stays the starting model, and the run says so."""
    out = tmp_path / "outputs"
    log = flwr_run(
        flower_env,
        f"num-server-rounds=2 local-steps=3 batch-size=4 lr=1.0 hf-repo-id='zk0-tests/best' output-dir='{out}'",
        ONE_ACTOR,
    )
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    run = runs[0]
    rounds = json.loads((run / "server" / "metrics_history.json").read_text())["rounds"]
    mse = [r["server-evaluate"]["action-mse"] for r in rounds]
    assert mse[1] > mse[0] and mse[2] > mse[0], f"the premise: every round is worse than round 0 ({mse})"
    assert [r["best"] for r in rounds] == [{"round": 0, "action-mse": mse[0]}] * 3
    assert "no round beat the starting model" in log.split("Done in ")[-1]

    best = run / "models" / "best"
    assert json.loads((best / "zk0_round.json").read_text())["round"] == 0
    entry = registry.get("synth-so100-eval")
    start = get_trainable(build_policy(RunConfig(), open_metadata(entry), entry, registry.model_cameras()))
    saved = SmolVLAPolicy.from_pretrained(best).state_dict()
    assert all((saved[n].numpy() == start[n].numpy()).all() for n in start), "models/best holds round 0's weights"
    card = (run / "hub" / "best_round_0" / "README.md").read_text()
    assert "| checkpoint | round 0, the lowest server action MSE of rounds 0-2 |" in card


def test_bad_run_config_fails_before_training_in_one_sentence(flower_env, tmp_path):
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"local-steps=0 output-dir='{out}'", ONE_ACTOR)
    assert "zk0: Run-config key 'local-steps' got 0; expected a value >= 1." in log
    assert not out.exists(), "nothing is written for a run that never starts"


def test_bf16_exchange_learns_like_fp32(flower_env, three_rounds, tmp_path):
    """The learning check, small: the three-round run (bf16 on the wire) ends within 10% of the same
    run's server action MSE with fp32 on the wire, and both learn."""
    out = tmp_path / "float32"
    log = flwr_run(flower_env, f"{THREE_ROUNDS} wire-dtype='float32' output-dir='{out}'", ONE_ACTOR)
    final = {}
    for wire, run in (("float32", next(out.iterdir(), None)), ("bfloat16", three_rounds[0])):
        assert run is not None, log[-3000:]
        rounds = json.loads((run / "server" / "metrics_history.json").read_text())["rounds"]
        assert [r["round"] for r in rounds] == [0, 1, 2, 3], log[-3000:]
        final[wire] = rounds[-1]["server-evaluate"]["action-mse"]
        assert final[wire] < 0.8 * rounds[0]["server-evaluate"]["action-mse"], f"{wire}: it learns at all"
    assert abs(final["bfloat16"] - final["float32"]) <= 0.10 * final["float32"], final


def test_one_client_sending_1000x_its_update_is_scaled_down_and_the_federation_keeps_learning(flower_env, tmp_path):
    """A bad client (zk0's ClientApp with its reply scaled, as ``python -m zk0.bench robust`` runs it):
    named once per round, scaled down to the other's size, and the global model still improves."""
    out = tmp_path / "outputs"
    app = scaled_client_app(tmp_path / "app", index=1, factor=1000.0)
    config = "num-server-rounds=2 local-steps=20 batch-size=8 lr=2e-3 eval-batches=1000 eval-frequency=2"
    log = flwr_run(flower_env, f"{config} output-dir='{out}'", ONE_ACTOR, app=app)
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    rounds = json.loads((runs[0] / "server" / "metrics_history.json").read_text())["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2], log[-3000:]
    server_log = (runs[0] / "server" / "server.log").read_text()
    for r in (1, 2):
        named = f"Round {r}: client 1 (synth-so100-stacking)'s update is"
        assert server_log.count(named) == 1, f"round {r}"
        scale = rounds[r]["clients"]["1"]["train"]["update-scale"]
        assert 5e-4 < scale < 2e-3, "scaled to the other's norm: about 1/1000"
        assert rounds[r]["clients"]["0"]["train"]["update-scale"] == 1.0
    mse = [r["server-evaluate"]["action-mse"] for r in rounds if "server-evaluate" in r]
    assert len(mse) == 2, "the start and the end are evaluated"
    assert mse[-1] < 0.8 * mse[0], f"it learns as test_bf16_exchange_learns_like_fp32's run does: {mse}"


def test_a_time_budget_and_a_deadline_name_who_was_cut_short_and_who_was_late(flower_env, tmp_path):
    """``local-time-s`` far below one step: every client takes its one step and says so (no
    straggler: none took less than half the fastest's steps). A
    ``round-deadline-s`` far below a round's work: round 1 (which builds the clients) waits for
    them; in every later round their updates are dropped, each round names them, the global
    model is kept, and the third round in a row warns that their owners' work is not counted."""
    out = tmp_path / "outputs"
    config = "num-server-rounds=4 local-steps=5 local-time-s=1e-6 round-deadline-s=0.01 eval-frequency=4"
    log = flwr_run(flower_env, f"{config} checkpoint-interval=4 output-dir='{out}'", ONE_ACTOR)
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    rounds = json.loads((runs[0] / "server" / "metrics_history.json").read_text())["rounds"]
    first = rounds[1]["clients"]
    assert [(c["train"]["local-steps"], c["train"]["num-examples"]) for c in first.values()] == [(1, 8), (1, 8)]
    assert "late" not in rounds[1]
    assert "Round 1/4: 2 clients trained, 1 of 5 steps, train loss " in log  # alike: no one straggles
    for record in rounds[2:5]:
        assert record["late"] == {"clients": [0, 1], "nodes": []}, record
    assert "Round 2/4: 0 clients trained, stragglers: client 0 (late), client 1 (late), " in log
    server_log = (runs[0] / "server" / "server.log").read_text()
    warning = "Client 0 (synth-so100-pickplace) has sent no update within round-deadline-s=0.01 in each of the last 3"
    assert server_log.count(warning) == 1, server_log[-3000:]
    report = (runs[0] / "report.html").read_text()
    assert "late (not counted)" in report and "client 0, client 1" in report


def test_flwr_stop_ends_the_run_at_once(flower_env, tmp_path):
    """`flwr stop` in the middle of 60 short rounds. Flower signals the ServerApp's process when the
    SuperLink refuses its next request (a log upload after the next logged line: up to a round or
    two under load, Flower's latency, only bounded here), then lets the ServerApp's thread run on
    for up to 5 s while it exits (several rounds): zk0's ServerApp writes no round file after
    Flower's "Task stopped" line, and says so."""
    import re
    import subprocess
    import sys
    import time
    from datetime import datetime

    from zk0.deployment.simulation import CONNECTION

    out = tmp_path / "outputs"
    flwr = str(Path(sys.executable).with_name("flwr"))
    config = f"num-server-rounds=60 local-steps=1 batch-size=4 eval-batches=1 checkpoint-interval=30 output-dir='{out}'"
    started = subprocess.run(
        [flwr, "run", ".", CONNECTION, "--federation-config", ONE_ACTOR, "--run-config", config],
        env=flower_env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    run_id = re.search(r"Successfully started run (\d+)", started.stdout + started.stderr)[1]
    deadline = time.monotonic() + 300
    while not list(out.glob("*/server/round_1.json")):
        assert time.monotonic() < deadline, "round 1 was never written"
        time.sleep(0.05)
    subprocess.run([flwr, "stop", run_id, CONNECTION], env=flower_env, capture_output=True, timeout=60, check=True)
    (run_dir,) = out.iterdir()
    server_log = run_dir / "server" / "server.log"
    deadline = time.monotonic() + 15
    while not (signalled := re.search(r"^(\S+ \S+) \|.*Task stopped by user", server_log.read_text(), re.M)):
        assert time.monotonic() < deadline, "Flower did not signal the ServerApp within 15 s of `flwr stop`"
        time.sleep(0.05)
    time.sleep(6)  # past Flower's 5 s force exit
    at_signal = datetime.strptime(signalled[1], "%Y-%m-%d %H:%M:%S.%f").timestamp()
    after = {p.name: p.stat().st_mtime - at_signal for p in (run_dir / "server").glob("round_*.json")}
    late = {name: round(s, 2) for name, s in after.items() if s > 0.5}  # a write already past its check may end
    assert not late, f"written this many seconds after the signal: {late}"
    assert "the server writes nothing more" in server_log.read_text()


@pytest.mark.allowance(420)
def test_the_full_size_model_takes_a_step_checkpoints_and_loads_in_lerobot(flower_env, tmp_path):
    """The path every owner with a GPU takes, stepped on the CPU: SmolVLA on a SmolVLM2-500M-shaped
    backbone (random weights), one client, one local step at batch 1. Its update is the 199.79 MB
    docs/performance.md gives for bf16 on the wire, the round is checkpointed, and models/best
    loads with lerobot's from_pretrained with every one of the 450,046,176 parameters."""
    from zk0.data.assets import FULL_SIZE_BACKBONE, ensure_backbone

    ensure_backbone(kind=FULL_SIZE_BACKBONE)  # what `zk0 assets` makes once per machine
    out = tmp_path / "outputs"
    # No client evaluation: a full-size forward on one thread is 10-20 s, and the server's two (round 0
    # and round 1, which models/best needs) already step that path.
    config = "model='full-size' num-server-rounds=1 local-steps=1 batch-size=1 eval-batches=1 min-train-clients=1"
    config += " fraction-evaluate=0"
    log = flwr_run(flower_env, f"{config} output-dir='{out}'", cpu_federation(1, actors=1))
    history = list(out.glob("*/server/metrics_history.json"))
    assert len(history) == 1, log[-6000:]  # a run that died early (out of memory beside another test) says why
    runs = [history[0].parent.parent]
    rounds = json.loads(history[0].read_text())["rounds"]
    assert [r["round"] for r in rounds] == [0, 1], log[-3000:]
    train = rounds[1]["clients"]["0"]["train"]
    assert train["local-steps"] == 1 and train["num-examples"] == 1
    assert abs(train["update-bytes"] / 199.79e6 - 1) < 0.001, train["update-bytes"]
    assert (runs[0] / "models" / "checkpoint_round_1" / "model.safetensors").is_file()
    policy = SmolVLAPolicy.from_pretrained(runs[0] / "models" / "best")
    assert sum(p.numel() for p in policy.parameters()) == 450_046_176
    assert "OutOfMemoryError" not in log and "Traceback" not in log
