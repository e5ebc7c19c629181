"""Bad datasets, written with lerobot's own writer and then broken, are refused in one sentence
before anything trains: by `zk0 check`, by a run's checks, by a client, by `zk0 supernode`; and
evaluation skips damaged held-out frames like training does."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from flwr.app import ArrayRecord, ConfigRecord, Context, Message, RecordDict
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from zk0.cli import main as zk0_main
from zk0.common import machine
from zk0.config import from_run_config
from zk0.data.registry import load_registry
from zk0.learning.preflight import check_federation

SERVER = """
[tool.zk0.datasets.synth-so100-eval]
repo_id = "zk0/synth_so100_eval"
synthetic = true
role = "server"
cameras = { front = "camera1", wrist = "camera2" }
"""


def write_dataset(
    root: Path, *, episodes: int = 4, frames: int = 12, joints: int = 6, cameras=("front",), one_file_each=False
) -> Path:
    """A small SO-100-like LeRobotDataset through lerobot's writer (real AV1 video)."""
    features = {
        "observation.state": {"dtype": "float32", "shape": (joints,), "names": None},
        "action": {"dtype": "float32", "shape": (joints,), "names": None},
        **{
            f"observation.images.{cam}": {
                "dtype": "video",
                "shape": (32, 32, 3),
                "names": ["height", "width", "channels"],
            }
            for cam in cameras
        },
    }
    dataset = LeRobotDataset.create(
        repo_id=f"someone/{root.name}",
        fps=10,
        root=root,
        features=features,
        robot_type="so100_follower",
        video_files_size_in_mb=1e-9 if one_file_each else None,  # every episode starts a new video file
    )
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        for _ in range(frames):
            frame = {
                "observation.state": rng.normal(size=joints).astype(np.float32),
                "action": rng.normal(size=joints).astype(np.float32),
                "task": "pick the cube",
            }
            for cam in cameras:
                frame[f"observation.images.{cam}"] = rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)
            dataset.add_frame(frame)
        with machine.ordinary_scheduling():  # as zk0's recorders: libsvtav1 would leave it real-time
            dataset.save_episode(parallel_encoding=False)
    dataset.finalize()
    return root


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("datasets") / "good")


def copy_of(good: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(good, tmp_path / "copy"))


def broken(kind: str, good: Path, tmp_path: Path) -> tuple[Path, str]:
    """A dataset broken as robot owners' datasets are; (its root, the cameras mapping to register)."""
    front = '{ front = "camera1" }'
    if kind == "no-camera":
        return write_dataset(tmp_path / "nocam", cameras=()), front
    if kind == "few-episodes":
        return write_dataset(tmp_path / "few", episodes=2), front
    if kind == "v2.1":
        root = copy_of(good, tmp_path)
        info = json.loads((root / "meta" / "info.json").read_text())
        (root / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v2.1"}))
        return root, front
    if kind == "seven-joints":
        return write_dataset(tmp_path / "seven", joints=7), front
    if kind == "unknown-camera":
        return copy_of(good, tmp_path), '{ top = "camera1" }'
    root = copy_of(good, tmp_path)
    video = next((root / "videos").rglob("*.mp4"))
    if kind == "missing-video":
        video.unlink()
    else:
        assert kind == "empty-video"
        video.write_bytes(b"")
    return root, front


EXPECTED = {
    "no-camera": "Dataset 'owner' records no camera; the policy needs at least one camera image.",
    "v2.1": "Dataset 'owner' (someone/{name}) is in an older LeRobot format; convert it to v3.0 with "
    "`python -m lerobot.scripts.convert_dataset_v21_to_v30 --repo-id=someone/{name}` and pin the new revision.",
    "seven-joints": "Dataset 'owner' has 'observation.state' of size [7]; the model expects [6] "
    "(every dataset of a federation must record the same arm).",
    "unknown-camera": "Dataset 'owner' has no camera 'top', which its registry entry maps; "
    "expected one of its cameras ['front'].",
    "missing-video": "Dataset 'owner' lacks 'videos/observation.images.front/chunk-000/file-000.mp4', which its "
    "episodes use, under '{root}'.",
    "empty-video": "Dataset 'owner' has an empty (0-byte) 'videos/observation.images.front/chunk-000/file-000.mp4' "
    "under '{root}'.",
    "few-episodes": "Dataset 'owner' has 2 episodes; expected at least 3 (eval-episodes=2 held out and one to train on).",
}


def registry_with(tmp_path: Path, root: Path, cameras: str) -> Path:
    file = tmp_path / "registry.toml"
    owner = f'[tool.zk0.datasets.owner]\nrepo_id = "someone/{root.name}"\nroot = "{root}"\ncameras = {cameras}\n'
    file.write_text(SERVER + owner)
    return file


@pytest.mark.parametrize("kind", sorted(EXPECTED))
def test_each_bad_dataset_is_refused_in_one_sentence_by_zk0_check_and_a_run(kind, good, tmp_path, capsys):
    root, cameras = broken(kind, good, tmp_path)
    registry_file = registry_with(tmp_path, root, cameras)
    expected = EXPECTED[kind].format(name=root.name, root=root)
    capsys.readouterr()  # what lerobot's writer printed

    assert zk0_main(["check", "--run-config", f"registry='{registry_file}' eval-episodes=2"]) == 2
    out, err = capsys.readouterr()
    assert err == f"zk0: {expected}\n" and out == ""
    # the ServerApp's check before round 1 of a simulation: every dataset, none skipped
    run = from_run_config({"registry": str(registry_file), "eval-episodes": 2})
    report = check_federation(run, load_registry(registry_file), clients=True, skip_absent=False)
    assert report.problems == [expected] and report.checked == ["synth-so100-eval"]


def test_a_client_refuses_its_bad_dataset_with_an_error_reply_naming_it(good, tmp_path, flower_task, isolated_logging):
    """What the ClientApp sends back: Flower's error reply, with zk0's sentence as the reason."""
    from zk0.client_app import _reply
    from zk0.common.errors import REFUSED

    root, cameras = broken("seven-joints", good, tmp_path)
    registry_file = registry_with(tmp_path, root, cameras)
    node_config = {"dataset": "owner", "output-dir": str(tmp_path / "out")}
    run_config = {"registry": str(registry_file)}
    context = Context(run_id=3, node_id=9, node_config=node_config, state=RecordDict(), run_config=run_config)
    config = {"server-round": 1, "run-name": "r", "shape:observation.state": [6], "shape:action": [6]}
    msg = Message(
        RecordDict({"config": ConfigRecord(config), "arrays": ArrayRecord()}), dst_node_id=9, message_type="train"
    )
    reply = _reply("train", msg, context)
    assert reply.has_error() and reply.error.code == REFUSED
    assert reply.error.reason == f"Client 0 (owner): {EXPECTED['seven-joints']}"


def test_supernode_with_a_bad_dataset_stops_before_connecting(good, tmp_path, capsys):
    root, cameras = broken("empty-video", good, tmp_path)
    registry_file = registry_with(tmp_path, root, cameras)
    capsys.readouterr()
    args = ["supernode", "--superlink", "127.0.0.1:1", "--insecure", "--dataset", "owner"]
    assert zk0_main([*args, "--registry", str(registry_file), "--output-dir", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"zk0: {EXPECTED['empty-video'].format(root=root)}\n"


def test_a_local_root_never_reaches_the_hub(good, tmp_path, monkeypatch):
    """A missing local file is named; lerobot would otherwise try to download it."""
    import huggingface_hub

    def no_network(*args, **kwargs):
        raise AssertionError("the Hub was asked")

    monkeypatch.setattr(huggingface_hub.HfApi, "list_repo_refs", no_network)  # lerobot's first Hub call
    root = copy_of(good, tmp_path)
    (root / "meta" / "tasks.parquet").unlink()
    run = from_run_config({"registry": str(registry_with(tmp_path, root, '{ front = "camera1" }'))})
    report = check_federation(run, load_registry(run.registry), skip_absent=False)
    assert report.problems == [
        f"Dataset 'owner' has no 'meta/tasks.parquet' under '{root}'; its metadata is incomplete."
    ]


def held_out_client(good_root: Path, tmp_path: Path, max_skip: float):
    """A client whose last (held-out) episode's video file is overwritten with garbage of its size."""
    from zk0.data.registry import DatasetEntry
    from zk0.federation.client import build_client

    root = write_dataset(tmp_path / "damaged", episodes=4, frames=16, one_file_each=True)
    videos = sorted((root / "videos").rglob("*.mp4"))
    assert len(videos) == 4, "one video file per episode"
    videos[-1].write_bytes(np.random.default_rng(1).integers(0, 255, videos[-1].stat().st_size, np.uint8).tobytes())
    entry = DatasetEntry(repo_id="someone/damaged", name="damaged", root=str(root), cameras={"front": "camera1"})
    run = from_run_config({"batch-size": 4, "eval-episodes": 2, "eval-batches": 8, "max-skip-fraction": max_skip})
    registry = load_registry()
    return build_client(run, entry, registry.model_cameras())


def test_evaluation_skips_and_counts_damaged_held_out_frames(good, tmp_path):
    from zk0.learning.training import evaluate

    client = held_out_client(good, tmp_path, max_skip=0.6)
    metrics = evaluate(client.bundle, client.split, client.eval_batches, 8, seed=0, max_skip=0.6)
    assert metrics["skipped-batches"] == 4 and metrics["num-examples"] == 16  # episode 2 read, episode 3 not
    assert np.isfinite(metrics["action-mse"])


def test_evaluation_past_max_skip_fraction_fails_in_one_sentence(good, tmp_path):
    from zk0.learning.training import TrainingError, evaluate

    client = held_out_client(good, tmp_path, max_skip=0.1)
    with pytest.raises(TrainingError) as failed:
        evaluate(client.bundle, client.split, client.eval_batches, 8, seed=0, max_skip=0.1)
    assert str(failed.value) == (
        "Dataset 'damaged': 3 of 7 held-out batches could not be decoded, more than max-skip-fraction=0.1."
    )


@pytest.mark.e2e
def test_a_simulation_whose_every_client_is_refused_stops_without_done_or_checkpoint(good, flower_env, tmp_path):
    """The real `flwr run`: one sentence per bad dataset, no traceback, exit code, nothing written."""
    from zk0.deployment.simulation import cpu_federation, flwr_run

    seven = write_dataset(tmp_path / "seven", joints=7)
    empty = copy_of(good, tmp_path)
    video = next((empty / "videos").rglob("*.mp4"))
    video.write_bytes(b"")
    registry_file = tmp_path / "registry.toml"
    registry_file.write_text(
        SERVER
        + f'[tool.zk0.datasets.owner]\nrepo_id = "someone/seven"\nroot = "{seven}"\ncameras = {{ front = "camera1" }}\n'
        + f'[tool.zk0.datasets.other]\nrepo_id = "someone/copy"\nroot = "{empty}"\ncameras = {{ front = "camera1" }}\n'
    )
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"registry='{registry_file}' output-dir='{out}'", cpu_federation(2, actors=1))
    first = EXPECTED["seven-joints"]
    second = EXPECTED["empty-video"].format(root=empty).replace("'owner'", "'other'")
    assert log.count(f"zk0: {first}") == 1 and log.count(f"zk0: {second}") == 1, log[-4000:]
    assert "Exit Code: " in log and "Done" not in log
    assert "Traceback" not in log, log[-4000:]
    assert not out.exists(), "nothing is written for a run that never starts"


@pytest.mark.e2e
def test_a_first_round_that_cannot_train_stops_the_run_with_each_clients_sentence(good, flower_env, tmp_path):
    """Videos that pass every metadata check but cannot be decoded: every client's round fails,
    so the run stops after round 1 with a non-zero exit, each sentence once, and no checkpoint."""
    from zk0.deployment.simulation import cpu_federation, flwr_run

    entries = ""
    for name in ("garbled-a", "garbled-b"):
        root = Path(shutil.copytree(good, tmp_path / name))
        for video in (root / "videos").rglob("*.mp4"):
            video.write_bytes(np.random.default_rng(2).integers(0, 255, video.stat().st_size, np.uint8).tobytes())
        entries += f'[tool.zk0.datasets.{name}]\nrepo_id = "someone/{name}"\nroot = "{root}"\ncameras = {{ front = "camera1" }}\n'
    registry_file = tmp_path / "registry.toml"
    registry_file.write_text(SERVER + entries)
    out = tmp_path / "outputs"
    log = flwr_run(flower_env, f"registry='{registry_file}' output-dir='{out}'", cpu_federation(2, actors=1))
    for index, name in enumerate(("garbled-a", "garbled-b")):
        sentence = (
            f"Round 1: Client {index} ({name}): Dataset '{name}': 3 of 3 training batches could not be decoded, "
            "more than max-skip-fraction=0.1."
        )
        assert log.count(sentence) == 1, log[-4000:]
    stop = "zk0: Round 1 got 0 usable update(s), fewer than min-train-clients=2, so this run cannot train"
    assert log.count(stop) == 1 and "Exit Code: " in log and "Done" not in log
    assert "Traceback" not in log, log[-4000:]
    (run_dir,) = out.iterdir()
    assert not (run_dir / "models").exists(), "no checkpoint of an untrained model"
    server_log = (run_dir / "server" / "server.log").read_text()
    assert stop.removeprefix("zk0: ") in server_log and "Traceback" in server_log, "the traceback is kept, in the file"
