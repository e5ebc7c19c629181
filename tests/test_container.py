"""The zk0 image, built and run for real: podman builds ./Dockerfile from a Debian base made here
with debootstrap, and ``./train.sh --docker`` runs the quick federation inside it as the host user.

The base and the image stay in podman's store, so a second run of the suite rebuilds only what
changed (the project's code: one layer). On a fresh machine ./test.sh builds both before pytest
starts (zk0_ensure_image in scripts/setup.sh), so the suite's own time does not include them.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from tests.conftest import require_tool
from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.loopback import tool

pytestmark = pytest.mark.container


def engine_env() -> dict[str, str]:
    """The environment podman runs in: this machine's containers.conf (scripts/setup.sh writes it)."""
    done = subprocess.run(
        ["bash", "-c", "source scripts/setup.sh && zk0_containers_conf"],
        cwd=PROJECT_ROOT, capture_output=True, text=True, check=True,
    )  # fmt: skip
    return {**os.environ, "CONTAINERS_CONF": done.stdout.strip(), "ZK0_ENGINE": "podman"}


@pytest.fixture(scope="session")
def image() -> dict[str, str]:
    """The zk0 image, built (or found current) by the same function ./test.sh calls; its environment."""
    require_tool("podman", "podman")
    require_tool("debootstrap", "debootstrap")
    env = engine_env()
    done = subprocess.run(
        ["bash", "-c", "source scripts/setup.sh && zk0_ensure_image"],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=3600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return env


@pytest.mark.allowance(240)
def test_the_quick_run_in_the_container_writes_the_hosts_outputs_as_the_host_user(image):
    """``./train.sh --docker``: the run's report and models/best land in the host's outputs/,
    owned by whoever ran it (not the image's user 10001), with the figures the run's JSON holds."""
    folder = f"container-test-{uuid.uuid4().hex[:8]}"
    host = PROJECT_ROOT / "outputs" / folder
    try:
        as_a_user = {k: v for k, v in image.items() if k not in {"CONTAINERS_CONF", "ZK0_ENGINE"}}  # as a user runs it
        done = subprocess.run(
            [str(PROJECT_ROOT / "train.sh"), "--docker", "-r", f"output-dir='/workspace/outputs/{folder}'"],
            env=as_a_user, capture_output=True, text=True, timeout=900, check=False,
        )  # fmt: skip
        printed = done.stdout + done.stderr
        assert done.returncode == 0, printed[-4000:]
        (run_dir,) = host.iterdir()
        assert (run_dir / "report.html").is_file() and (run_dir / "models" / "best" / "model.safetensors").is_file()
        owners = {p.stat().st_uid for p in run_dir.rglob("*")}
        assert owners == {os.getuid()}, f"files owned by {owners}; expected only the host user {os.getuid()}"
        history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
        mse = history["rounds"][-1]["server-evaluate"]["action-mse"]
        assert f"server action MSE {mse:.4g}" in printed, printed[-2000:]
        assert printed.splitlines()[-1] == f"[zk0] Outputs: {run_dir}", "the host's path, not the container's"
        assert f"[zk0] Report: {run_dir / 'report.html'}\n" in printed, "the host's path, not the container's"
    finally:
        shutil.rmtree(host, ignore_errors=True)


def test_the_image_has_what_train_sh_needs_and_no_test_tools(image):
    """procps (train.sh stops its SuperLink with pgrep and ps), the base's Python >= 3.12, torchcodec
    loading with the base's FFmpeg, zk0's simulator plugin registered with lerobot, and no pytest
    (the test extra stays out of the image)."""
    script = (
        "command -v pgrep ps tmux >/dev/null && python -c 'import sys; assert sys.version_info >= (3, 12)' "
        "&& python -c 'import torchcodec.decoders' "
        "&& python -c 'import importlib.metadata as m; m.distribution(\"lerobot_env_zk0\")' "
        "&& ! python -c 'import pytest' 2>/dev/null && echo ok"
    )
    done = subprocess.run(
        ["podman", "run", "--rm", "zk0", "bash", "-c", script],
        env=image, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert done.stdout.strip() == "ok", done.stdout + done.stderr


def compose(root: Path, env: dict[str, str], *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``podman-compose <args>`` on the compose file in ``root``, as the README runs it."""
    command = [tool("podman-compose"), *args]
    return subprocess.run(command, cwd=root, env=env, capture_output=True, text=True, timeout=timeout, check=False)


@pytest.mark.allowance(300)
def test_a_tls_federation_in_containers_runs_two_rounds_with_each_partys_files_in_its_own_folder(image, tmp_path):
    """deploy/compose.yaml, step by step as the README gives it: a SuperLink and two SuperNodes,
    each in its own container, TLS and SuperNode authentication, the run submitted with `flwr run`
    from the operator's container. The server's run folder is in server/, each owner's client log
    in that owner's folder and nowhere else."""
    root = tmp_path / "deploy"
    root.mkdir()
    for name in ("compose.yaml", "flower.toml"):
        shutil.copy(PROJECT_ROOT / "deploy" / name, root)
    certs = subprocess.run(
        [tool("zk0"), "certs", "--host", "superlink", "--supernode", "alice",
         "--supernode", "bob"], cwd=root, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert certs.returncode == 0, certs.stderr
    for party in ("server", "alice", "bob"):
        for folder in ("outputs", "cache"):
            (root / party / folder).mkdir(parents=True)
    env = {k: v for k, v in image.items() if k not in {"ZK0_UID", "ZK0_GID"}}
    unset = compose(root, env, "run", "--rm", "flwr", "supernode", "list", "zk0")
    assert unset.returncode != 0 and "unset-ZK0_UID" in unset.stdout + unset.stderr, "named, not a traceback"
    assert "Traceback" not in unset.stdout + unset.stderr
    (root / ".env").write_text(f"ZK0_UID={os.getuid()}\nZK0_GID={os.getgid()}\n")  # as the README writes it
    try:
        assert compose(root, env, "up", "-d", "superlink").returncode == 0
        deadline = time.monotonic() + 180
        while compose(root, env, "run", "--rm", "flwr", "supernode", "list", "zk0").returncode != 0:
            assert time.monotonic() < deadline, compose(root, env, "logs", "superlink").stdout[-3000:]
            time.sleep(3)
        for owner in ("alice", "bob"):
            done = compose(
                root, env, "run", "--rm", "flwr", "supernode", "register", f"certificates/supernodes/{owner}.pub", "zk0"
            )
            assert done.returncode == 0, done.stdout + done.stderr
        assert compose(root, env, "up", "-d", "alice", "bob").returncode == 0
        config = "num-server-rounds=2 local-steps=2 batch-size=4 eval-batches=1 output-dir='/workspace/outputs'"
        done = compose(root, env, "run", "--rm", "flwr", "run", ".", "zk0", "--stream", "--run-config", config, timeout=1200)
        logs = compose(root, env, "logs").stdout[-6000:]
        (record,) = (root / "server" / "outputs").glob("*/server/metrics_history.json")
        run_dir = record.parent.parent
        history = json.loads(record.read_text())
        assert [r["round"] for r in history["rounds"]] == [0, 1, 2], done.stdout[-3000:] + logs
        assert sorted(history["clients"].values()) == ["synth-so100-pickplace", "synth-so100-stacking"]
        for owner, dataset in (("alice", "synth-so100-pickplace"), ("bob", "synth-so100-stacking")):
            (log,) = (root / owner / "outputs" / run_dir.name / "clients").glob("client_*/client.log")
            assert "Round 2 train" in log.read_text(), f"{owner}'s client trained in round 2 and logged it at home"
            assert (root / owner / "cache" / "zk0").is_dir(), f"{owner}'s dataset is in their own folder"
        assert not list(run_dir.glob("clients/*/client.log")), "no owner's log is on the server"
        assert {p.stat().st_uid for p in root.rglob("*")} == {os.getuid()}, "every file is the host user's"
    finally:
        compose(root, env, "down", "-t", "5", timeout=300)
