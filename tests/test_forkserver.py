"""The SuperExec's fork server: each ClientApp process is Flower's `flwr-clientapp` with the
arguments Flower chose, forked from a process that imported Flower once, and each simulation's
process `flwr-simulation`, forked from one that imported PyTorch and lerobot too. (The loopback
deployment test runs whole federations through the first, with TLS, authentication and the
submitted code; every simulated federation of the suite runs through the second.)"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil
import pytest

from zk0.deployment.forkserver import RAY_WORKER_SERVER, ForkServer


def wait_for(capfd, text: str, timeout: float = 60) -> str:
    seen = ""
    deadline = time.monotonic() + timeout
    while text not in seen and time.monotonic() < deadline:
        time.sleep(0.1)
        seen += "".join(capfd.readouterr())  # what the children printed, and what they logged
    return seen


@contextmanager
def serving(server: bool = False) -> Iterator[ForkServer]:
    """A fork server (a SuperLink's with ``server``), closed as its SuperExec's exit closes it."""
    forks = ForkServer(server)
    try:
        yield forks
    finally:
        forks.process.stdin.close()
    assert forks.process.wait(timeout=30) == 0, "the fork server ends with its SuperExec's pipe"


def test_a_forked_clientapp_runs_flowers_command_with_the_arguments_it_was_given(capfd):
    with serving() as server:
        assert server.start(["flwr-clientapp", "--help"], quiet=False)
        printed = wait_for(capfd, "--runtime-api-address")
        assert "usage: flwr-clientapp" in printed, printed


def test_without_its_fork_server_the_superexec_starts_clientapps_as_flower_does():
    from loguru import logger

    said: list[str] = []
    sink = logger.add(said.append, format="{message}")
    try:
        server = ForkServer()
        server.process.kill()
        server.process.wait()
        assert not server.start(["flwr-clientapp", "--help"], quiet=False)
        assert not server.start(["flwr-clientapp", "--help"], quiet=False), "and goes on without it"
    finally:
        logger.remove(sink)
    assert len(said) == 1 and "the ClientApp fork server exited (code -9)" in said[0], said


def test_zk0s_supernode_starts_zk0s_superexec_with_flowers_arguments(monkeypatch, capfd):
    from flwr.supernode import start_client_internal as loop

    from zk0 import internals

    monkeypatch.setattr(loop, "subprocess", loop.subprocess)  # this process's loop gets Flower's back afterwards
    internals.start_superexec_as([sys.executable, "-c", "import sys; print('superexec', sys.argv[1:])"])
    assert loop.subprocess.Popen(["flower-superexec", "--insecure", "--parent-pid", "1"]).wait(timeout=30) == 0
    assert "superexec ['--insecure', '--parent-pid', '1']" in wait_for(capfd, "superexec")
    other = loop.subprocess.Popen([sys.executable, "-c", "print('other')"], stdout=subprocess.PIPE, text=True)
    assert other.communicate(timeout=30)[0] == "other\n", "other commands start as they did"


@pytest.mark.slow  # its fork server imports lerobot
def test_a_superlinks_fork_server_runs_simulations_and_serverapps_with_torch_and_lerobot_loaded(capfd):
    """The SuperLink's fork server (``server``) forks ``flwr-simulation`` and ``flwr-serverapp`` as
    Flower's own commands, from a process that has imported the ServerApp's libraries. A
    SuperNode's starts ClientApps only."""
    with serving(server=True) as server:
        for command in ("flwr-simulation", "flwr-serverapp"):
            assert server.start([command, "--help"], quiet=False)
            assert f"usage: {command}" in wait_for(capfd, f"usage: {command}", timeout=180), command
    with serving() as supernodes:
        assert supernodes.start(["flwr-simulation", "--help"], quiet=False)
        said = wait_for(capfd, "not 'flwr-simulation'")
        assert "zk0: this fork server starts flwr-clientapp, not 'flwr-simulation'." in said, said


def test_zk0s_superlink_starts_zk0s_superexec_for_servers_with_flowers_arguments(monkeypatch, capfd):
    import importlib

    from zk0 import internals

    link = importlib.import_module("flwr.superlink.cli.flower_superlink")
    monkeypatch.setattr(link, "subprocess", link.subprocess)  # Flower's comes back afterwards
    internals.start_superlinks_superexec_as([sys.executable, "-c", "import sys; print('superexec', sys.argv[1:])"])
    started = link.subprocess.Popen(["flower-superexec", "--insecure", "--parent-pid", "1"])
    assert started.wait(timeout=30) == 0, "the SuperLink keeps the handle it stops its SuperExec with"
    assert "superexec ['--insecure', '--parent-pid', '1']" in wait_for(capfd, "superexec")


@contextmanager
def ray_worker_server() -> Iterator[str]:
    """A Ray worker fork server, forked from a process of its own as a SuperLink's fork server
    forks it; its socket's path. It ends within a second of that process."""
    host = subprocess.Popen(
        [sys.executable, "-c", "from zk0.deployment.forkserver import start_ray_worker_server as s; "
         "print(s(), flush=True); import sys; sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        path = host.stdout.readline().strip()
        (server,) = psutil.Process(host.pid).children()
        assert server.name() == RAY_WORKER_SERVER, "named for `ps` and the benchmarks' memory watch"
        yield path
    finally:
        host.stdin.close()
        host.wait(timeout=30)


WORKER = """import os, sys, time
if sys.argv[1] == "--wait":
    import ray._raylet

    ray._raylet.setproctitle("ray::ClientAppActor")  # as Ray's worker names itself
print(sys.argv[1:], os.environ["RAY_JOB_ID"], os.getcwd(), os.getpid(), flush=True)
print("said on stderr", file=sys.stderr, flush=True)
if sys.argv[1] == "--wait":
    time.sleep(600)
sys.exit(3)
"""


def test_a_ray_worker_is_forked_with_rays_arguments_environment_folder_and_output_and_dies_with_its_starter(tmp_path):
    """Ray starts a simulation's worker as ``rayworker`` + its worker script and arguments: the
    worker runs forked from the fork server, as ``python <script> <arguments>`` would, with the
    environment, folder and output files Ray gave; the ``rayworker`` exits with its code, and
    killing the ``rayworker`` (as Ray stops a worker that has not registered) kills the worker.
    It can rename itself as Ray's workers do, which the benchmarks' memory watch reads.
    Without the fork server, the worker starts as Ray would start it."""
    from zk0.bench.watch import role_of
    from zk0.deployment import rayworker

    script = tmp_path / "default_worker.py"
    script.write_text(WORKER)
    (tmp_path / "run").mkdir()
    env = {**os.environ, "RAY_JOB_ID": "01000000"}
    starter = [sys.executable, "-m", "zk0.deployment.rayworker", str(script)]
    with ray_worker_server() as path:
        assert path.endswith("workers.sock"), path
        env[rayworker.SOCKET_ENV] = path
        with (tmp_path / "worker.out").open("w") as out, (tmp_path / "worker.err").open("w") as err:
            started = subprocess.Popen([*starter, "--a=1"], env=env, cwd=tmp_path / "run", stdout=out, stderr=err)
            assert started.wait(timeout=60) == 3, "the worker's exit code"
        said = (tmp_path / "worker.out").read_text().split()
        assert said[:3] == ["['--a=1']", "01000000", str(tmp_path / "run")], said
        assert int(said[3]) != started.pid, "forked, not started by the rayworker"
        assert (tmp_path / "worker.err").read_text() == "said on stderr\n"

        waiting = subprocess.Popen([*starter, "--wait"], env=env, stdout=subprocess.PIPE, text=True)
        worker = psutil.Process(int(waiting.stdout.readline().split()[-1]))
        try:
            assert worker.name() == "ray::ClientAppActor" and role_of(worker) == "client", "named as Ray names it"
        finally:
            waiting.kill()
            worker.wait(timeout=10)  # raises if it outlives its rayworker
    deadline = time.monotonic() + 10
    while Path(path).parent.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not Path(path).parent.exists(), "the fork server ends with its parent and removes its socket"

    del env[rayworker.SOCKET_ENV]
    alone = subprocess.run([*starter, "--a=1"], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert alone.returncode == 3 and alone.stdout.split()[0] == "['--a=1']", alone.stderr
