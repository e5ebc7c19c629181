"""The SuperExec's fork server: each ClientApp process is Flower's `flwr-clientapp` with the
arguments Flower chose, forked from a process that imported Flower once. (The loopback deployment
test runs whole federations through it, with TLS, authentication and the submitted code.)"""

from __future__ import annotations

import subprocess
import sys
import time

from zk0.deployment.forkserver import ForkServer


def wait_for(capfd, text: str, timeout: float = 60) -> str:
    seen = ""
    deadline = time.monotonic() + timeout
    while text not in seen and time.monotonic() < deadline:
        time.sleep(0.1)
        seen += capfd.readouterr().out
    return seen


def test_a_forked_clientapp_runs_flowers_command_with_the_arguments_it_was_given(capfd):
    server = ForkServer()
    try:
        assert server.start(["flwr-clientapp", "--help"], quiet=False)
        printed = wait_for(capfd, "--runtime-api-address")
        assert "usage: flwr-clientapp" in printed, printed
    finally:
        server.process.stdin.close()
    assert server.process.wait(timeout=30) == 0, "the fork server ends with its SuperExec's pipe"


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
    assert loop.subprocess.Popen(["flower-superexec", "--insecure", "--parent-pid", "1"]) is None
    assert "superexec ['--insecure', '--parent-pid', '1']" in wait_for(capfd, "superexec")
    other = loop.subprocess.Popen([sys.executable, "-c", "print('other')"], stdout=subprocess.PIPE, text=True)
    assert other.communicate(timeout=30)[0] == "other\n", "other commands start as they did"
