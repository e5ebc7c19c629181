"""The production path, offline: hub-style datasets under HF_LEROBOT_HOME, resume after a crash,
dataset refusals, and the real-run preset."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from zk0.cli import main as zk0_main
from zk0.common import machine
from zk0.config import RunConfig
from zk0.data.assets import ensure_dataset
from zk0.data.loaders import DataError, open_metadata
from zk0.data.registry import PROJECT_ROOT, DatasetEntry, load_registry
from zk0.deployment.simulation import CONNECTION, cpu_federation, local_federation, start_superlink, stop_superlink
from zk0.learning.policy import PolicyError, build_policy

# Hub-style ids for the generated datasets, as robot owners' registries name community datasets.
HUB_IDS = {
    "synth-so100-pickplace": "lerobot/svla_so100_pickplace",
    "synth-so100-stacking": "lerobot/svla_so100_stacking",
    "synth-so100-eval": "lerobot/svla_so101_pickplace",
}
REGISTRY = """
[tool.zk0.datasets.pickplace]
repo_id = "lerobot/svla_so100_pickplace"
revision = "v3.0"
cameras = {{ front = "camera1", wrist = "camera2" }}

[tool.zk0.datasets.stacking]
repo_id = "lerobot/svla_so100_stacking"
revision = "v3.0"
cameras = {{ laptop = "camera1", phone = "camera2" }}

[tool.zk0.datasets.eval]
repo_id = "lerobot/svla_so101_pickplace"
revision = "v3.0"
role = "server"
cameras = {{ front = "camera1", wrist = "camera2" }}
"""


@pytest.fixture(scope="module")
def hub_home(tmp_path_factory):
    """An HF_LEROBOT_HOME laid out as the Hub cache lays datasets out, filled with generated data."""
    home = tmp_path_factory.mktemp("lerobot-home")
    for name, repo_id in HUB_IDS.items():
        shutil.copytree(ensure_dataset(name), home / repo_id)
    registry = home / "registry.toml"
    registry.write_text(REGISTRY.format())
    return home, registry


def flwr(env: dict, run_config: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            str(Path(sys.executable).with_name("flwr")),
            "run",
            str(PROJECT_ROOT),
            CONNECTION,
            "--stream",
            "--federation-config",
            cpu_federation(2, actors=1),
            "--run-config",
            run_config,
        ],
        env=env,
        cwd=PROJECT_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@pytest.mark.e2e
def test_resume_after_sigkill_finishes_every_round_once(tmp_path, hub_home):
    home, registry = hub_home
    out = tmp_path / "outputs"
    config = (
        f"num-server-rounds=4 local-steps=2 batch-size=4 checkpoint-interval=2 eval-batches=1 "
        f"registry='{registry}' server-eval-dataset='eval' output-dir='{out}'"
    )
    offline_hub = {"HF_LEROBOT_HOME": str(home), "HF_HUB_OFFLINE": "1"}
    with local_federation(tmp_path / "flwr-home", offline_hub) as env:
        first = flwr(env, config)
        deadline = time.monotonic() + 600
        while not list(out.glob("*/models/checkpoint_round_2")):
            assert first.poll() is None and time.monotonic() < deadline, first.stdout.read()[-3000:]
            time.sleep(0.2)
        stop_superlink(env, kill=True)  # SIGKILL the SuperLink, the simulation and its Ray workers
        first.communicate(timeout=120)
        (run_dir,) = out.iterdir()
        assert not (run_dir / "models" / "checkpoint_round_4").exists()

        start_superlink(env)  # the restarted SuperLink, as `flwr run` would start it
        second = flwr(env, f"{config} resume-from='{run_dir}'")
        log, _ = second.communicate(timeout=900)
    assert list(out.iterdir()) == [run_dir], "the resumed run continues in the same folder"
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    assert [r["round"] for r in history["rounds"]] == [0, 1, 2, 3, 4], log[-3000:]
    assert all("server-evaluate" in r for r in history["rounds"])
    assert (run_dir / "models" / "checkpoint_round_4" / "model.safetensors").is_file()
    assert "Resuming" in (run_dir / "server" / "server.log").read_text()
    # hub-style ids resolved against HF_LEROBOT_HOME, offline, through the real run's code path
    assert history["clients"] == {"0": "pickplace", "1": "stacking"}
    trained = [history["rounds"][r]["clients"]["0"]["train"] for r in (1, 2, 3, 4)]
    assert all(t["num-examples"] == 8 for t in trained)
    lrs = [t["lr"] for t in trained]  # one cosine over the run: the resumed rounds continue it
    assert lrs == sorted(lrs, reverse=True) and len(set(lrs)) == 4, lrs


@pytest.mark.slow  # a process of its own, which imports lerobot
def test_hub_style_entry_opens_from_lerobot_home(hub_home):
    home, registry = hub_home
    script = (
        "from zk0.data.registry import load_registry; from zk0.data.loaders import open_metadata;"
        f"r = load_registry({str(registry)!r}); m = open_metadata(r.get('lerobot/svla_so100_stacking'));"
        "print(m.root, m.total_episodes)"
    )
    env = {"HF_LEROBOT_HOME": str(home), "HF_HUB_OFFLINE": "1", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.split() == [str(home / "lerobot/svla_so100_stacking"), "6"]


def test_older_format_dataset_is_refused_with_the_conversion_command(tmp_path):
    copy = tmp_path / "old"
    shutil.copytree(ensure_dataset("synth-so100-eval"), copy)
    info = json.loads((copy / "meta" / "info.json").read_text())
    (copy / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    entry = DatasetEntry(repo_id="someone/old_so100", name="old", root=str(copy), cameras={"front": "camera1"})
    with pytest.raises(DataError) as err:
        open_metadata(entry)
    assert "'old'" in str(err.value) and "convert_dataset_v21_to_v30 --repo-id=someone/old_so100" in str(err.value)


def test_dataset_without_joint_state_is_refused_with_its_name(tmp_path, registry):
    dataset = LeRobotDataset.create(
        repo_id="someone/no_state",
        fps=10,
        root=tmp_path / "no_state",
        features={
            "action": {"dtype": "float32", "shape": (6,), "names": None},
            "observation.images.front": {
                "dtype": "video",
                "shape": (32, 32, 3),
                "names": ["height", "width", "channels"],
            },
        },
    )
    for _ in range(3):
        dataset.add_frame(
            {
                "action": np.zeros(6, np.float32),
                "observation.images.front": np.zeros((32, 32, 3), np.uint8),
                "task": "t",
            }
        )
    with machine.ordinary_scheduling():  # as zk0's recorders: libsvtav1 would leave it real-time
        dataset.save_episode(parallel_encoding=False)
    dataset.finalize()
    entry = DatasetEntry(
        repo_id="someone/no_state", name="no-state", root=str(tmp_path / "no_state"), cameras={"front": "camera1"}
    )
    with pytest.raises(PolicyError, match="Dataset 'no-state' has no 'observation.state' feature"):
        build_policy(RunConfig(), open_metadata(entry), entry, registry.model_cameras())


def test_real_run_preset_validates_and_lists_community_datasets(capsys):
    assert zk0_main(["check", "--preset", "so100", "--print"]) == 0
    merged = capsys.readouterr().out
    assert "model='lerobot/smolvla_base'" in merged and "batch-size=64" in merged and "proximal-mu=0.01" in merged
    registry = load_registry("configs/so100-registry.toml")
    assert len(registry.clients) >= 8
    assert all(e.revision and not e.synthetic for e in registry.entries)
    assert registry.get("svla-so101-pickplace").role == "server"
