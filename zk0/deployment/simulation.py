"""Run the zk0 app with the real `flwr run` on a private local simulation SuperLink.

Benchmarks and tests use this so they exercise exactly what users run: the Flower CLI
builds the app bundle, a local SuperLink runs the ServerApp and the simulated
SuperNodes. A private ``FLWR_HOME`` and free ports keep it apart from any other
SuperLink on the machine, and the SuperLink is stopped afterwards.

`flwr run` starts a missing local SuperLink itself but gives it 15 s, which a 2-core machine
already running another federation can exceed; so the SuperLink is started here first, with
the arguments `flwr run` would use and a patient deadline, and `flwr run` finds it up. It is
Flower's SuperLink run as ``python -m zk0.deployment.superlink``, which forks each run's
``flwr-simulation`` and its Ray workers from processes that have imported PyTorch and lerobot
once: a benchmark's or a test worker's many federations each start about 20 s of CPU sooner.
(``./train.sh`` runs the SuperLink `flwr run` starts, Flower's own, and the suite's quick-run
tests run it that way.)
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from pathlib import Path

import psutil

from zk0.data.registry import PROJECT_ROOT

CONNECTION = "zk0-sim"


def free_port() -> int:
    """A TCP port nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


FLOWER_CONFIG = f'[superlink]\ndefault = "{CONNECTION}"\n\n[superlink.{CONNECTION}]\naddress = ":local:"\n'


@contextmanager
def local_federation(home: Path, extra_env: dict[str, str] | None = None) -> Iterator[dict[str, str]]:
    """The environment for `flwr run` against a private SuperLink (started with ``extra_env`` in
    its environment, which the ServerApp and ClientApps inherit); stops that SuperLink on exit."""
    home.mkdir(parents=True, exist_ok=True)
    (home / "config.toml").write_text(FLOWER_CONFIG)
    port = free_port()
    env = {
        **os.environ,
        "FLWR_HOME": str(home),
        "FLWR_LOCAL_SUPERLINK_HTTP_API_PORT": str(port),
        "FLWR_LOCAL_CONTROL_API_PORT": str(free_port()),
        "FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION": "1",
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        **(extra_env or {}),
    }
    try:
        start_superlink(env)
        yield env
    finally:
        stop_superlink(env)


def start_superlink(env: dict[str, str], timeout_s: float = 180.0) -> None:
    """Start the private simulation SuperLink with the arguments `flwr run` would give it, and wait until it answers."""
    runtime = Path(env["FLWR_HOME"]) / "local-superlink"
    runtime.mkdir(parents=True, exist_ok=True)
    port = env["FLWR_LOCAL_SUPERLINK_HTTP_API_PORT"]
    command = [
        sys.executable, "-m", "zk0.deployment.superlink", "--insecure", "--simulation", "--isolation", "subprocess",
        "--control-api-address", f"127.0.0.1:{env['FLWR_LOCAL_CONTROL_API_PORT']}",
        "--host", "127.0.0.1", "--port", port,
        "--log-file", str(runtime / "superlink.log"), "--database", str(runtime / "state.db"),
    ]  # fmt: skip
    process = subprocess.Popen(
        command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    direct = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # localhost, never via a proxy
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"The SuperLink exited with code {process.returncode}; see {runtime / 'superlink.log'}.")
        try:
            with direct.open(f"http://127.0.0.1:{port}/health", timeout=1.0):
                return  # answered 2xx (urlopen raises on errors)
        except OSError:
            pass
        time.sleep(0.2)
    process.kill()
    raise RuntimeError(f"The SuperLink did not answer within {timeout_s:.0f} s; see {runtime / 'superlink.log'}.")


def superlink_tree(env: dict[str, str]) -> list[psutil.Process]:
    """The SuperLink on this environment's port (zk0's, or the one `flwr run` started: ``./train.sh``'s)
    and every process under it (simulation, Ray)."""
    marker = f"--port {env['FLWR_LOCAL_SUPERLINK_HTTP_API_PORT']}"
    for proc in psutil.process_iter(["cmdline"]):
        cmdline = " ".join(proc.info["cmdline"] or [])
        if ("zk0.deployment.superlink" in cmdline or "flower-superlink" in cmdline) and marker in cmdline:
            return [proc, *proc.children(recursive=True)]
    return []


def stop_superlink(env: dict[str, str], kill: bool = False) -> None:
    """Terminate (or, with ``kill``, SIGKILL as a crash would) the SuperLink and its children."""
    tree = superlink_tree(env)
    for proc in tree:
        try:
            proc.kill() if kill else proc.terminate()
        except psutil.NoSuchProcess:
            pass
    psutil.wait_procs(tree, timeout=30)


def cpu_federation(num_supernodes: int, actors: int | None = None) -> str:
    """A federation config: ``num_supernodes`` CPU clients, run by ``actors`` Ray workers (default: one per core)."""
    config = f"num-supernodes={num_supernodes} client-resources-num-cpus=1 client-resources-num-gpus=0.0"
    return config + (f" init-args-num-cpus={actors}" if actors else "")


def flwr_run(
    env: dict[str, str], run_config: str, federation: str, timeout: float = 3600, app: Path = PROJECT_ROOT
) -> str:
    """`flwr run <app> --stream` (zk0 itself by default) with a run config and a federation config;
    returns what it printed."""
    flwr = str(Path(sys.executable).with_name("flwr"))
    done = subprocess.run(
        [
            flwr,
            "run",
            str(app),
            CONNECTION,
            "--stream",
            "--federation-config",
            federation,
            "--run-config",
            run_config,
        ],
        env=env,
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    return done.stdout + done.stderr


_PROCESS_SUPERLINK: dict[str, str] = {}


def process_superlink() -> dict[str, str]:
    """The environment of this process's own private SuperLink, started on first use and stopped
    when the process exits: a benchmark's federations (and a test worker's) share it, instead of
    starting a SuperLink for each."""
    if not _PROCESS_SUPERLINK:
        home = Path(tempfile.mkdtemp(prefix="zk0-flwr-"))
        federation = ExitStack()
        _PROCESS_SUPERLINK.update(federation.enter_context(local_federation(home)))
        federation.callback(shutil.rmtree, home, ignore_errors=True)
        atexit.register(federation.close)
    return dict(_PROCESS_SUPERLINK)


def run_federation(
    run_config: str,
    clients: int,
    output_dir: Path,
    name: str,
    app: Path = PROJECT_ROOT,
    watch: Callable[[dict[str, str]], AbstractContextManager] | None = None,
) -> dict | None:
    """`flwr run` with ``clients`` CPU clients on this process's SuperLink, or, with ``watch``, on
    a SuperLink of its own: ``watch(env)`` is entered while it runs (zk0.bench.scale samples the
    memory of the processes under that SuperLink, this run's alone); the run's metric history.

    For benchmarks: on failure it prints the end of Flower's log and one sentence, and returns None.
    """
    with ExitStack() as stack:
        if watch is None:
            env = process_superlink()
        else:
            env = stack.enter_context(local_federation(Path(stack.enter_context(tempfile.TemporaryDirectory()))))
            stack.enter_context(watch(env))
        log = flwr_run(env, f"{run_config} output-dir='{output_dir}'", cpu_federation(clients), app=app)
    runs = sorted(output_dir.glob("*/server/metrics_history.json"), key=lambda p: p.stat().st_mtime)
    if not runs or "Exit Code: " in log:
        print(log[-4000:], file=sys.stderr)
        print(f"{name}: the federation did not finish; its log is above.", file=sys.stderr)
        return None
    return {"run-dir": str(runs[-1].parent.parent), **json.loads(runs[-1].read_text())}
