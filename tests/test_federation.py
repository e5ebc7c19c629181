"""End to end: the real `flwr run` against a local simulation SuperLink, offline, 2 clients x 2 rounds."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from lerobot.processor import PolicyProcessorPipeline
from lerobot.processor.converters import batch_to_transition, transition_to_batch

REPO = Path(__file__).resolve().parents[1]
FLWR = str(Path(sys.executable).with_name("flwr"))
FLOWER_CONFIG = """
[superlink]
default = "test"

[superlink.test]
address = ":local:"
options.num-supernodes = 2
options.backend.client-resources.num-cpus = 1
options.backend.client-resources.num-gpus = 0.0
"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def flower_env(tmp_path_factory):
    """A private Flower home and SuperLink ports; the SuperLink `flwr run` starts is stopped afterwards."""
    home = tmp_path_factory.mktemp("flwr-home")
    (home / "config.toml").write_text(FLOWER_CONFIG)
    port, control = free_port(), free_port()
    env = {
        **os.environ,
        "FLWR_HOME": str(home),
        "FLWR_LOCAL_SUPERLINK_HTTP_API_PORT": str(port),
        "FLWR_LOCAL_CONTROL_API_PORT": str(control),
        "FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION": "1",
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
    }
    yield env
    subprocess.run(["pkill", "-f", f"flower-superlink.*--port {port}"], check=False)


def flwr_run(env: dict, overrides: str) -> str:
    done = subprocess.run(
        [FLWR, "run", str(REPO), "test", "--stream", "--run-config", overrides],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=900, check=False,
    )
    return done.stdout + done.stderr


def test_two_clients_two_rounds_write_every_artifact(flower_env, tmp_path):
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"num-server-rounds=2 local-steps=3 batch-size=4 checkpoint-interval=1 output-dir='{out}'")
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    run = runs[0]
    server = run / "server"
    for name in ["server.log", "metrics_history.json", "policy_loss.png", "action_mse.png",
                 "round_0.json", "round_1.json", "round_2.json"]:
        assert (server / name).stat().st_size > 0, name
    history = json.loads((server / "metrics_history.json").read_text())
    assert history["clients"] == {"0": "synth-so100-pickplace", "1": "synth-so100-stacking"}
    assert [r["round"] for r in history["rounds"]] == [0, 1, 2]
    last = history["rounds"][-1]
    assert set(last["clients"]) == {"0", "1"}, "clients are named by their short index, not node ids"
    for index, client in last["clients"].items():
        assert client["dataset"] == history["clients"][index]
        assert client["train"]["num-examples"] == 3 * 4
        assert {"train-loss", "proximal-loss", "grad-norm", "step-time", "peak-gpu-gib", "host-rss-gib"} <= set(client["train"])
        assert {"policy-loss", "action-mse"} <= set(client["evaluate"])
        client_dir = run / "clients" / f"client_{index}"
        assert "Round 2 train" in (client_dir / "client.log").read_text()
        assert json.loads((client_dir / "round_2.json").read_text())["train"]["num-examples"] == 12
    assert {"policy-loss", "action-mse"} <= set(last["server-evaluate"])
    assert {"policy-loss", "action-mse"} <= set(last["aggregate-evaluate"])
    models = run / "models"
    assert sorted(p.name for p in models.iterdir()) == ["checkpoint_round_1", "checkpoint_round_2"]

    checkpoint = models / "checkpoint_round_2"
    policy = SmolVLAPolicy.from_pretrained(checkpoint)
    trainable = [n for n, p in policy.named_parameters() if p.requires_grad]
    assert last["global-arrays"]["tensors"] == len(trainable) < len(list(policy.parameters()))
    payload = 4 * sum(p.numel() for p in policy.parameters() if p.requires_grad)  # fp32 trainable weights
    assert payload <= last["global-arrays"]["bytes"] < 1.05 * payload

    preprocessor = PolicyProcessorPipeline.from_pretrained(
        checkpoint, "policy_preprocessor.json", to_transition=batch_to_transition, to_output=transition_to_batch
    )
    dataset = LeRobotDataset("zk0/synth_so100_stacking", root=Path(os.environ["ZK0_CACHE"]) / "datasets/zk0/synth_so100_stacking")
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


def test_bad_run_config_fails_before_training_in_one_sentence(flower_env, tmp_path):
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"local-steps=0 output-dir='{out}'")
    assert "zk0: Run-config key 'local-steps' got 0; expected a value >= 1." in log
    assert not out.exists(), "nothing is written for a run that never starts"
