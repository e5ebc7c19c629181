"""The server's one progress line per round, from what the round recorded."""

from __future__ import annotations

from types import SimpleNamespace

import torch
from flwr.app import ArrayRecord, MetricRecord

from zk0.artifacts.run_folder import History
from zk0.config import RunConfig
from zk0.federation import round_artifacts
from zk0.federation.round_artifacts import RoundArtifacts


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
        "Round 1/4: 2 clients trained, 1 refused, train loss 0.5, server action MSE 61.54, 30.0 s/round, "
        "about 1m 30s left"
    )
    assert artifacts.progress(2) == (
        "Round 2/4: 1 client trained, train loss -, server action MSE not evaluated, 40.0 s/round, about 1m 20s left"
    )


def test_with_a_time_budget_the_round_line_says_the_steps_the_clients_took(tmp_path, monkeypatch):
    clock = iter([100.0, 130.0])
    monkeypatch.setattr(round_artifacts, "time", SimpleNamespace(perf_counter=lambda: next(clock)))
    history = History(tmp_path, {0: "a", 1: "b"}, {})
    run = RunConfig(num_server_rounds=2, local_steps=75, local_time_s=60.0)
    artifacts = RoundArtifacts(run, None, None, None, history, None, {}, first_round=1)
    history.add_client(1, "train", 0, {"train-loss": 0.4, "local-steps": 75})
    history.add_client(1, "train", 1, {"train-loss": 0.6, "local-steps": 18})
    assert artifacts.progress(1).startswith(
        "Round 1/2: 2 clients trained, 18-75 of 75 steps, stragglers: client 1 (18 steps), train loss -, "
    )


def server_artifacts(run: RunConfig, tmp_path, client_parts, registry) -> RoundArtifacts:
    """The server's writer for ``run`` on the first client's policy, writing under ``tmp_path``."""
    from zk0.artifacts.tracking import Tracker

    history = History(tmp_path, {0: registry.clients[0].name}, {})
    server = registry.get(run.server_eval_dataset)
    return RoundArtifacts(run, registry, client_parts[0], server, history, Tracker.start(run, tmp_path), {}, 1)


def test_models_best_keeps_the_lowest_server_mse_round_zero_included(tmp_path, client_parts, registry):
    """Round 0 (the starting model) is the best until a round beats it; models/best is rewritten only
    then, holds that round's weights and says which round it is; a worse round changes nothing."""
    import json

    from safetensors.torch import load_file

    from zk0.learning.policy import get_trainable

    run = RunConfig(num_server_rounds=3, checkpoint_interval=10)
    artifacts = server_artifacts(run, tmp_path, client_parts, registry)
    start = get_trainable(client_parts[0])
    names = list(start)
    rounds = {r: ArrayRecord({n: t + 0.01 * r for n, t in start.to_torch_state_dict().items()}) for r in (1, 2, 3)}
    best = tmp_path / "models" / "best"

    def best_weights():
        saved = load_file(best / "model.safetensors")
        return {n: saved[n] for n in names}

    artifacts.round_ended(0, start, MetricRecord({"action-mse": 50.0, "policy-loss": 1.0}), {})
    artifacts.round_ended(1, rounds[1], MetricRecord({"action-mse": 80.0, "policy-loss": 2.0}), {})
    artifacts.finish_writes()  # what the next round's evaluation and end wait for
    assert json.loads((best / "zk0_round.json").read_text())["round"] == 0
    assert all(torch.equal(best_weights()[n], torch.from_numpy(start[n].numpy())) for n in names)
    assert artifacts.summary() == (
        "no round beat the starting model (server action MSE 50), so models/best is round 0, the model this run started from"
    )
    artifacts.round_ended(2, rounds[2], MetricRecord({"action-mse": 40.0, "policy-loss": 0.5}), {})
    artifacts.round_ended(3, rounds[3], MetricRecord({"action-mse": 45.0, "policy-loss": 0.4}), {})
    assert json.loads((best / "zk0_round.json").read_text()) == {
        "round": 2,
        "server-evaluate": {"action-mse": 40.0, "policy-loss": 0.5},
    }
    assert all(torch.equal(best_weights()[n], torch.from_numpy(rounds[2][n].numpy())) for n in names)
    assert artifacts.summary() == "models/best is round 2 (server action MSE 40; round 0: 50)"
    recorded = json.loads((tmp_path / "server" / "metrics_history.json").read_text())["rounds"]
    assert [r["best"]["round"] for r in recorded] == [0, 0, 2, 2]
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == ["best", "checkpoint_round_3"]


def test_a_best_round_that_keeps_a_checkpoint_links_models_best_to_its_files(tmp_path, client_parts, registry):
    """When the best round is also a checkpoint round, models/best is the checkpoint's files, not a
    second copy of the model (1.8 GB full-size), without the server optimiser's state; a later
    best replaces models/best and leaves the checkpoint as it was."""
    import json

    from safetensors.torch import load_file

    from zk0.artifacts.run_folder import SERVER_STATE_FILE
    from zk0.learning.policy import get_trainable

    run = RunConfig(num_server_rounds=4, checkpoint_interval=2)
    artifacts = server_artifacts(run, tmp_path, client_parts, registry)
    start = get_trainable(client_parts[0])
    rounds = {r: ArrayRecord({n: t + 0.01 * r for n, t in start.to_torch_state_dict().items()}) for r in (1, 2, 3)}
    models = tmp_path / "models"
    name = next(iter(start))

    def weights(folder: str) -> torch.Tensor:
        return load_file(models / folder / "model.safetensors")[name]

    artifacts.round_ended(0, start, MetricRecord({"action-mse": 50.0}), {})
    artifacts.round_ended(1, rounds[1], MetricRecord({"action-mse": 80.0}), {})
    artifacts.round_ended(2, rounds[2], MetricRecord({"action-mse": 40.0}), {})
    best, checkpoint = models / "best", models / "checkpoint_round_2"
    assert (best / "model.safetensors").stat().st_ino == (checkpoint / "model.safetensors").stat().st_ino
    assert (checkpoint / SERVER_STATE_FILE).is_file() and not (best / SERVER_STATE_FILE).exists()
    assert json.loads((best / "zk0_round.json").read_text()) == {"round": 2, "server-evaluate": {"action-mse": 40.0}}
    assert sorted(p.name for p in best.rglob("*")) == sorted(
        p.name for p in checkpoint.rglob("*") if p.name != SERVER_STATE_FILE
    )
    assert torch.equal(weights("best"), torch.from_numpy(rounds[2][name].numpy()))

    artifacts.round_ended(3, rounds[3], MetricRecord({"action-mse": 30.0}), {})
    artifacts.finish_writes()
    assert torch.equal(weights("best"), torch.from_numpy(rounds[3][name].numpy()))
    assert torch.equal(weights("checkpoint_round_2"), torch.from_numpy(rounds[2][name].numpy()))
    assert sorted(p.name for p in models.iterdir()) == ["best", "checkpoint_round_2"]


def test_only_the_newest_checkpoints_are_kept_and_models_best_outlives_its_own(tmp_path, client_parts, registry):
    """keep-checkpoints=2, a checkpoint every round: once round N's is complete, round N-2's goes;
    models/best, hard links to round 1's files, stays whole when round 1's checkpoint is removed.
    Rollout videos alike: the newest two and the best round's (the ones the report shows)."""
    from safetensors.torch import load_file

    from zk0.artifacts.run_folder import checkpoints
    from zk0.learning.policy import get_trainable

    run = RunConfig(num_server_rounds=4, checkpoint_interval=1, keep_checkpoints=2)
    artifacts = server_artifacts(run, tmp_path, client_parts, registry)
    start = get_trainable(client_parts[0])
    name = next(iter(start))
    rounds = {r: ArrayRecord({n: t + 0.01 * r for n, t in start.to_torch_state_dict().items()}) for r in (1, 2, 3, 4)}
    videos = tmp_path / "server" / "videos"
    videos.mkdir(parents=True)

    def ended(r: int, mse: float) -> None:  # with closed-loop evaluation a round leaves its video first
        (videos / f"round_{r}.mp4").write_bytes(b"video")
        artifacts.round_ended(r, rounds.get(r, start), MetricRecord({"action-mse": mse}), {})

    ended(0, 50.0)
    ended(1, 10.0)  # the best, for good
    ended(2, 20.0)
    assert [r for r, _ in checkpoints(tmp_path)] == [1, 2]
    for r in (3, 4):
        ended(r, 30.0)
    artifacts.finish_writes()
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == [
        "best",
        "checkpoint_round_3",
        "checkpoint_round_4",
    ]
    assert sorted(p.name for p in videos.iterdir()) == ["round_1.mp4", "round_3.mp4", "round_4.mp4"]  # the report's
    best = load_file(tmp_path / "models" / "best" / "model.safetensors")[name]
    assert torch.equal(best, torch.from_numpy(rounds[1][name].numpy()))

    every = RunConfig(num_server_rounds=3, checkpoint_interval=1, keep_checkpoints=0)
    artifacts = server_artifacts(every, tmp_path / "every", client_parts, registry)
    for r in (0, 1, 2, 3):
        artifacts.round_ended(r, rounds.get(r, start), MetricRecord({"action-mse": 50.0 - r}), {})
    artifacts.finish_writes()
    assert [r for r, _ in checkpoints(tmp_path / "every")] == [1, 2, 3]


def test_a_middle_rounds_best_is_written_while_the_next_round_trains(tmp_path, client_parts, registry):
    """A middle round's models/best (1.8 GB full-size) is not written before the round ends, when
    the clients would wait for it, but in a thread while they train; it takes the server's policy
    only when the policy is free (here held, as the next round's evaluation holds it)."""
    import json
    import threading

    from zk0.learning.policy import get_trainable

    run = RunConfig(num_server_rounds=3, checkpoint_interval=10)
    artifacts = server_artifacts(run, tmp_path, client_parts, registry)
    start = get_trainable(client_parts[0])
    better = ArrayRecord({n: t + 0.01 for n, t in start.to_torch_state_dict().items()})
    best = tmp_path / "models" / "best"
    artifacts.round_ended(0, start, MetricRecord({"action-mse": 50.0}), {})
    with client_parts[0].lock:
        ender = threading.Thread(target=artifacts.round_ended, args=(1, better, MetricRecord({"action-mse": 40.0}), {}))
        ender.start()
        ender.join(timeout=60)
        assert not ender.is_alive(), "round 1 ended only once models/best was written"
        assert not best.exists()
    artifacts.finish_writes()
    assert json.loads((best / "zk0_round.json").read_text())["round"] == 1


def test_a_failed_write_of_models_best_ends_the_run_at_the_next_round(tmp_path, client_parts, registry, monkeypatch):
    """An error in the thread that writes models/best (a full disk) is not lost with the thread: the
    next round's end raises it."""
    import pytest

    from zk0.learning.policy import get_trainable

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    run = RunConfig(num_server_rounds=3, checkpoint_interval=10)
    artifacts = server_artifacts(run, tmp_path, client_parts, registry)
    start = get_trainable(client_parts[0])
    better = ArrayRecord({n: t + 0.01 for n, t in start.to_torch_state_dict().items()})
    artifacts.round_ended(0, start, MetricRecord({"action-mse": 50.0}), {})
    monkeypatch.setattr(round_artifacts, "save_checkpoint", disk_full)
    artifacts.round_ended(1, better, MetricRecord({"action-mse": 40.0}), {})
    with pytest.raises(OSError, match="No space left on device"):
        artifacts.round_ended(2, better, MetricRecord({"action-mse": 45.0}), {})
