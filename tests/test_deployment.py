"""Flower's Deployment Engine on loopback: TLS SuperLink with SuperNode authentication, two robot
owners on their own datasets, strangers refused, and a SuperNode that dies mid-run."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from zk0.certs import make_federation_certs
from zk0.registry import PROJECT_ROOT
from zk0.simulation import free_port

BIN = Path(sys.executable).parent


@dataclass
class Federation:
    root: Path
    env: dict
    address: str
    processes: list[subprocess.Popen] = field(default_factory=list)

    def start(self, name: str, *args: str) -> subprocess.Popen:
        """A `zk0` operator command in its own process group, logging to <root>/<name>.log."""
        log = (self.root / f"{name}.log").open("w")
        proc = subprocess.Popen(
            [str(BIN / "zk0"), *args], env=self.env, cwd=self.root, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        self.processes.append(proc)
        return proc

    def supernode(self, name: str, dataset: str, *extra: str) -> subprocess.Popen:
        return self.start(
            name, "supernode", "--superlink", self.address, "--certs", "certs", "--dataset", dataset,
            "--runtime-port", str(free_port()), *extra,
        )  # fmt: skip

    def flwr(self, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
        return subprocess.run(
            [str(BIN / "flwr"), *args], env=self.env, cwd=PROJECT_ROOT, capture_output=True, text=True,
            timeout=timeout, check=False,
        )  # fmt: skip

    def log(self, name: str) -> str:
        return (self.root / f"{name}.log").read_text()


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> None:
    """Signal the process group (the Flower process and what it started); SIGKILL what lingers."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, sig)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        pass
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def federation(tmp_path_factory):
    """A TLS SuperLink with SuperNode auth and two registered, running SuperNodes."""
    root = tmp_path_factory.mktemp("deployment")
    make_federation_certs(root / "certs", [], ["robot-1", "robot-2", "stranger"])
    port = free_port()
    home = root / "flwr-home"
    home.mkdir()
    (home / "config.toml").write_text(
        f'[superlink]\ndefault = "lan"\n\n[superlink.lan]\naddress = "127.0.0.1:{port}"\n'
        f'root-certificates = "{root / "certs" / "ca.crt"}"\n'
    )
    env = {**os.environ, "FLWR_HOME": str(home), "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    env.pop("HF_TOKEN", None)
    fed = Federation(root, env, f"127.0.0.1:{port}")
    fed.start("superlink", "superlink", "--certs", "certs", "--address", fed.address)
    try:
        deadline = time.monotonic() + 60
        while fed.flwr("supernode", "list", "lan").returncode != 0:
            assert time.monotonic() < deadline, fed.log("superlink")[-2000:]
            time.sleep(1)
        for name in ("robot-1", "robot-2"):
            done = fed.flwr("supernode", "register", str(root / "certs" / "supernodes" / f"{name}.pub"), "lan")
            assert done.returncode == 0, done.stdout + done.stderr
        fed.supernode("robot-1", "synth-so100-pickplace", "--key", "robot-1")
        fed.supernode("robot-2", "synth-so100-stacking", "--key", "robot-2")
        yield fed
    finally:
        for proc in reversed(fed.processes):
            stop(proc)


def history(out: Path) -> tuple[Path, dict]:
    (run_dir,) = out.iterdir()
    return run_dir, json.loads((run_dir / "server" / "metrics_history.json").read_text())


def test_authenticated_supernodes_train_and_strangers_are_refused(federation):
    stranger = federation.supernode("stranger", "synth-so101-reach", "--key", "stranger")
    plaintext = federation.supernode("plaintext", "synth-so101-sorting", "--insecure")
    assert stranger.wait(timeout=120) != 0, "an unregistered key is refused"
    assert "Failed to activate SuperNode" in federation.log("stranger")

    out = federation.root / "outputs-1"
    done = federation.flwr(
        "run", ".", "lan", "--stream", "--run-config",
        f"num-server-rounds=2 local-steps=2 batch-size=4 eval-batches=1 output-dir='{out}'",
    )  # fmt: skip
    run_dir, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1, 2], done.stdout[-3000:]
    assert record["clients"] == {"0": "synth-so100-pickplace", "1": "synth-so100-stacking"}
    assert (run_dir / "models" / "checkpoint_round_2" / "model.safetensors").is_file()
    # Each message runs in a fresh flwr-clientapp process; training continues from Context.state.
    client_log = (run_dir / "clients" / "client_0" / "client.log").read_text()
    assert "Round 2 train" in client_log
    assert record["rounds"][2]["clients"]["0"]["train"]["lr"] > 0

    assert plaintext.poll() is None and "Connection attempt failed" in federation.log("plaintext")
    stop(plaintext)
    nodes = federation.flwr("supernode", "list", "lan", "--format", "json").stdout
    assert nodes.count('"online"') == 2, nodes


def test_a_supernode_killed_during_round_2_is_named_and_the_run_completes(federation):
    out = federation.root / "outputs-2"
    run = subprocess.Popen(
        [str(BIN / "flwr"), "run", ".", "lan", "--stream", "--run-config",
         f"num-server-rounds=3 local-steps=2 batch-size=4 eval-batches=1 min-train-clients=1 output-dir='{out}'"],
        env=federation.env, cwd=PROJECT_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 300
    while not list(out.glob("*/server/round_1.json")):
        assert run.poll() is None and time.monotonic() < deadline
        time.sleep(0.5)
    robot_2 = federation.processes[2]
    stop(robot_2, signal.SIGKILL)
    log, _ = run.communicate(timeout=600)
    run_dir, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1, 2, 3], log[-3000:]
    assert set(record["rounds"][3]["clients"]) == {"0"}, "the remaining client carries on"
    server_log = (run_dir / "server" / "server.log").read_text()
    assert "no usable update from node" in server_log and "(client 1)" in server_log
