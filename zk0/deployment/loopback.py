"""A Deployment Engine federation on this machine, as robot owners run it across machines.

One TLS SuperLink with SuperNode authentication and one ``zk0 supernode`` per robot owner,
each started by the same ``zk0`` operator commands the docs show, each SuperNode in its own
working folder with its own output folder (nothing shared but the CA certificate and the
SuperLink's address), and ``flwr run`` against it. The deployment test and
``python -m zk0.bench deployment`` use it, so what they measure is what users run.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.certs import make_federation_certs
from zk0.deployment.simulation import free_port

BIN = Path(sys.executable).parent
CONNECTION = "lan"


def tool(name: str) -> str:
    """A command of this environment (beside its Python, else on PATH): zk0, flwr."""
    found = shutil.which(name, path=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    if found is None:
        raise RuntimeError(f"The command {name!r} is not installed beside {sys.executable} or on PATH.")
    return found


@dataclass
class LoopbackFederation:
    """Operator commands against one SuperLink; each process logs to ``<root>/<name>.log``."""

    root: Path
    env: dict
    address: str
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, *args: str, cwd: Path | None = None) -> subprocess.Popen:
        """A ``zk0`` command in its own process group (its Flower process and what that starts)."""
        log = (self.root / f"{name}.log").open("w")
        proc = subprocess.Popen(
            [tool("zk0"), *args], env=self.env, cwd=cwd or self.root, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        self.processes[name] = proc
        return proc

    def supernode(self, name: str, dataset: str, *extra: str) -> subprocess.Popen:
        """A robot owner's SuperNode, working in ``<root>/<name>/`` with its outputs in ``outputs/`` there."""
        home = self.root / name
        home.mkdir(exist_ok=True)
        return self.start(
            name, "supernode", "--superlink", self.address, "--certs", str(self.root / "certs"),
            "--dataset", dataset, "--runtime-port", str(free_port()), "--output-dir", "outputs", *extra,
            cwd=home,
        )  # fmt: skip

    def register(self, *keys: str) -> None:
        for key in keys:
            done = self.flwr("supernode", "register", str(self.root / "certs" / "supernodes" / f"{key}.pub"))
            if done.returncode != 0:
                raise RuntimeError(f"Registering SuperNode key {key} failed: {done.stdout}{done.stderr}")

    def flwr(self, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
        """``flwr <command> ... lan`` (the connection name is appended where Flower expects it)."""
        command = [*args, CONNECTION] if args[0] == "supernode" else list(args)
        return subprocess.run(
            [tool("flwr"), *command], env=self.env, cwd=PROJECT_ROOT, capture_output=True, text=True,
            timeout=timeout, check=False,
        )  # fmt: skip

    def run_app(self, run_config: str, app: Path = PROJECT_ROOT, timeout: float = 1800) -> subprocess.CompletedProcess:
        """``flwr run <app> lan --stream`` with ``run_config``; returns when the run ends."""
        return self.flwr("run", str(app), CONNECTION, "--stream", "--run-config", run_config, timeout=timeout)

    def run_history(self, run_config: str, out: Path, who: str, timeout: float = 1800) -> dict | None:
        """``run_app`` with its outputs in ``out``: the run's metric history and folder (``run-dir``),
        or None after the end of its log and one sentence naming ``who`` ran it."""
        done = self.run_app(f"{run_config} output-dir='{out}'", timeout=timeout)
        runs = sorted(out.glob("*/server/metrics_history.json"))
        if not runs or "Exit Code: " in done.stdout:
            print(done.stdout[-4000:] + done.stderr[-2000:], file=sys.stderr)
            print(f"{who}: the deployment run did not finish; its log is above.", file=sys.stderr)
            return None
        return {"run-dir": str(runs[-1].parent.parent), **json.loads(runs[-1].read_text())}

    def log(self, name: str) -> str:
        return (self.root / f"{name}.log").read_text()

    def stop(self, name: str, sig: int = signal.SIGTERM) -> None:
        """Signal a process group; SIGKILL what lingers after 20 s."""
        proc = self.processes[name]
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=20)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)

    def process_tree(self) -> list[psutil.Process]:
        """Every process of this federation now: each one this object started, all under it, and
        the SuperNodes' warm workers (started by a one-message ClientApp process in a session of
        their own, they outlive it and leave the tree; each names its SuperNode's process)."""
        tree = []
        for proc in self.processes.values():
            with contextlib.suppress(psutil.Error):
                parent = psutil.Process(proc.pid)
                tree += [parent, *parent.children(recursive=True)]
        return tree + warm_workers_of({p.pid for p in tree})

    def stop_all(self, sig: int = signal.SIGTERM, grace_s: float = 20) -> None:
        """Signal every process group at once, then SIGKILL what lingers after ``grace_s``: stopped
        one at a time, the processes that were slow to exit added their waits up."""
        for proc in self.processes.values():
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
        deadline = time.monotonic() + grace_s
        for proc in self.processes.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)


def warm_workers_of(pids: set[int]) -> list[psutil.Process]:
    """The ``zk0.deployment.worker`` processes serving a SuperNode among ``pids`` (its pid ends their command)."""
    workers = []
    for proc in psutil.process_iter(["cmdline"]):
        cmdline = proc.info["cmdline"] or []
        if "zk0.deployment.worker" in cmdline and cmdline[-1].isdigit() and int(cmdline[-1]) in pids:
            workers.append(proc)
    return workers


@contextlib.contextmanager
def loopback_federation(
    root: Path, supernodes: dict[str, str], cpus: int | None = None, registry: str = "", later: tuple[str, ...] = ()
):
    """A running TLS federation under ``root``: ``supernodes`` maps key names to datasets, looked
    up in ``registry`` (default: pyproject.toml's), which the runs' config must name too.

    Also creates a key pair named ``stranger`` that is never registered, and one for each name in
    ``later``: owners who join mid-run (the test registers the key and starts the SuperNode). Its processes get a
    temporary directory of their own that starts empty, as a new machine's does (what a
    SuperNode keeps there, such as its warm worker's folder, is created in the order a first
    start creates it). Stops everything and removes that directory on exit.
    """
    make_federation_certs(root / "certs", [], [*supernodes, *later, "stranger"])
    machine_tmp = Path(tempfile.mkdtemp(prefix="zk0-machine-"))  # short: the worker's socket lives there
    port = free_port()
    home = root / "flwr-home"
    home.mkdir(parents=True, exist_ok=True)
    (home / "config.toml").write_text(
        f'[superlink]\ndefault = "{CONNECTION}"\n\n[superlink.{CONNECTION}]\naddress = "127.0.0.1:{port}"\n'
        f'root-certificates = "{root / "certs" / "ca.crt"}"\n'
    )
    env = {
        **os.environ, "FLWR_HOME": str(home), "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}",
        "TMPDIR": str(machine_tmp),
    }  # fmt: skip
    env.pop("HF_TOKEN", None)
    fed = LoopbackFederation(root, env, f"127.0.0.1:{port}")
    try:
        fed.start("superlink", "superlink", "--certs", "certs", "--address", fed.address)
        deadline = time.monotonic() + 120
        while fed.flwr("supernode", "list").returncode != 0:
            if time.monotonic() > deadline or fed.processes["superlink"].poll() is not None:
                raise RuntimeError(f"The SuperLink did not start: {fed.log('superlink')[-2000:]}")
            time.sleep(1)
        fed.register(*supernodes)
        for key, dataset in supernodes.items():
            extra = [*(["--cpus", str(cpus)] if cpus else []), *(["--registry", registry] if registry else [])]
            fed.supernode(key, dataset, "--key", key, *extra)
        yield fed
    finally:
        fed.stop_all()
        shutil.rmtree(machine_tmp, ignore_errors=True)
