"""An owner's personal model: fine-tuned from the global model on the owner's own data when the
client evaluates, judged beside it, kept as a lerobot policy folder on the owner's machine, and
never sent: the client's update is the same, byte for byte, with and without it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from flwr.app import ConfigRecord, Context, RecordDict
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

from zk0 import app_fingerprint
from zk0.config import from_run_config
from zk0.federation import client
from zk0.federation.wire import EVALUATE_ROUND, decode, encode
from zk0.learning.policy import backbone_fingerprint, trainable_tensors

pytestmark = pytest.mark.usefixtures("flower_task", "isolated_logging")

RUN = {"batch-size": 4, "local-steps": 3, "lr": 8e-3, "personal-lr": 8e-3, "num-server-rounds": 2, "eval-batches": 2,
       "personal-frequency": 1}  # fmt: skip


def messages(registry, personal_steps: int):
    """The global model (the starting one) as a round-1 train message and a round-2 train message
    that first evaluates what it receives, as the server sends them to client 0."""
    run_config = {**RUN, "personal-steps": personal_steps}
    start = client.build_client(from_run_config(run_config), registry.clients[0], registry.model_cameras())
    arrays = encode(trainable_tensors(start.bundle), start.run.wire_dtype)
    config = {"proximal-mu": 0.0, "run-name": "r", "app-fingerprint": app_fingerprint(),
              "backbone-fingerprint": backbone_fingerprint(start.bundle)}  # fmt: skip
    rounds = [RecordDict({"arrays": arrays, "config": ConfigRecord({**config, "server-round": 1})})]
    rounds.append(
        RecordDict({"arrays": arrays, "config": ConfigRecord({**config, "server-round": 2, EVALUATE_ROUND: 1})})
    )
    return run_config, rounds


def federate(registry, tmp_path, personal_steps: int, run_id: int, **keys) -> list[RecordDict]:
    run_config, rounds = messages(registry, personal_steps)
    run_config |= keys
    context = Context(run_id=run_id, node_id=3, node_config={"partition-id": 0, "output-dir": str(tmp_path)},
                      state=RecordDict(), run_config=run_config)  # fmt: skip
    return [client.handle("train", content, context) for content in rounds]


def test_the_personal_model_beats_the_global_one_on_its_owners_episodes_and_stays_there(registry, tmp_path):
    with_personal = federate(registry, tmp_path / "owner", personal_steps=60, run_id=71)
    without = federate(registry, tmp_path / "plain", personal_steps=0, run_id=72)
    client.release_sessions()

    # nothing personal travels: the updates are the same bytes, and the evaluation is metrics only
    for mine, plain in zip(with_personal, without, strict=True):
        assert set(mine) == set(plain)
        ours, theirs = mine["arrays"], plain["arrays"]
        assert all(np.array_equal(ours[k].numpy(), theirs[k].numpy()) for k in theirs)
    evaluation = dict(with_personal[1]["evaluation"])
    assert dict(without[1]["evaluation"]).keys() == {k for k in evaluation if not k.startswith("personal-")}
    assert evaluation["personal-action-mse"] < evaluation["action-mse"], (
        "60 steps on its own data help its own episodes"
    )
    assert {"personal-policy-loss", "personal-train-loss", "personal-s"} <= set(evaluation)

    # kept on the owner's machine, under its output folder, as a policy lerobot loads
    folder = tmp_path / "owner" / "r" / "clients" / "client_0" / "models" / "personal"
    kept = json.loads((folder / "zk0_round.json").read_text())
    assert kept["round"] == 1 and kept["evaluate"]["personal-action-mse"] == evaluation["personal-action-mse"]
    loaded = SmolVLAPolicy.from_pretrained(folder)
    start = decode(with_personal[0]["arrays"], "bfloat16")  # what round 1 trained; the personal one differs from it
    params = dict(loaded.named_parameters())
    assert any(not np.allclose(params[name].detach().numpy(), value.numpy()) for name, value in start.items())
    assert not (tmp_path / "plain" / "r" / "clients" / "client_0" / "models").exists()


def test_by_default_a_client_fine_tunes_only_for_the_models_a_run_keeps(registry, tmp_path):
    """Round 1 of 2 is no checkpoint round (checkpoint-interval 5): its evaluation has no personal
    model and the owner's machine keeps none; personal-frequency says otherwise."""
    replies = federate(registry, tmp_path, personal_steps=2, run_id=73, **{"personal-frequency": 0})
    client.release_sessions()
    assert not any(key.startswith("personal-") for key in replies[1]["evaluation"])
    assert not (tmp_path / "r" / "clients" / "client_0" / "models").exists()

    def rounds(**keys) -> list[int]:
        run = from_run_config({"num-server-rounds": 10, **keys})
        return [r for r in range(1, 11) if run.personalises_in(r)]

    assert rounds() == [5, 10]
    assert rounds(**{"checkpoint-interval": 3}) == [3, 6, 9, 10]
    assert rounds(**{"personal-frequency": 4}) == [4, 8, 10]


def test_a_simulated_owner_rolls_both_models_out_in_its_own_conditions(tmp_path):
    """With sim-eval-episodes an owner recorded in the simulator also judges the global and the personal
    model in its own set-up, each rate with its interval, and the folder keeps both figures."""
    from zk0.data.assets import ensure_dataset
    from zk0.data.registry import load_registry
    from zk0.federation.personal import build_personaliser

    registry = load_registry("configs/sim-registry.toml")
    entry = registry.get("sim-so101-left")
    ensure_dataset(entry.name)
    run = from_run_config({"registry": "configs/sim-registry.toml", "server-eval-dataset": "sim-so101-eval",
                           "model": "tiny-128", "batch-size": 2, "personal-steps": 2, "sim-eval-episodes": 2,
                           "sim-episode-length": 40})  # fmt: skip
    session = client.build_client(run, entry, registry.model_cameras())
    personaliser = build_personaliser(run, session.bundle, session.split, session.eval_batches)
    try:
        metrics = personaliser(1, tmp_path, {"action-mse": 1.0})
    finally:
        personaliser.close()
    for prefix in ("own-", "personal-own-"):
        assert metrics[f"{prefix}episodes"] == 2
        assert metrics[f"{prefix}success-low"] <= metrics[f"{prefix}success-rate"] <= metrics[f"{prefix}success-high"]
    assert 0.0 < metrics["personal-own-p"] <= 1.0, "McNemar's test of the two on the same episodes"
    kept = json.loads((tmp_path / "models" / "personal" / "zk0_round.json").read_text())["evaluate"]
    assert kept["action-mse"] == 1.0 and kept["personal-own-episodes"] == 2


def test_an_owner_is_told_which_model_to_run_by_success_beyond_the_noise():
    """The model that succeeds more often where McNemar's test says the difference is beyond the noise;
    otherwise the global model, which the federation goes on improving; nothing without both rollouts."""
    from zk0.learning.rates import model_choice

    rates = {"own-success-rate": 0.86, "personal-own-success-rate": 0.5}
    assert model_choice(rates | {"personal-own-p": 0.0004}) == "run the global model (McNemar p 0.0004)"
    assert model_choice({"own-success-rate": 0.52, "personal-own-success-rate": 0.9, "personal-own-p": 0.001}) == (
        "run the personal model (McNemar p 0.001)"
    )
    assert model_choice(rates | {"personal-own-p": 0.06}) == (
        "run the global model (no difference beyond the noise, McNemar p 0.06)"
    )
    assert model_choice(rates) == ""
