"""Flower's task processes forked from one that has already imported what they need, instead of started afresh.

Flower's SuperExec starts a new process for every task: a ``flwr-clientapp`` for every message on
a SuperNode (both isolation modes, flwr 1.41-1.43), a ``flwr-serverapp`` or ``flwr-simulation``
for every run on a SuperLink. Each pays Python's start and its imports before it does anything:
Flower's (FastAPI, SQLAlchemy, httpx, the protobufs; about a second of CPU, two on a busy machine)
for a ClientApp, every round; Flower's, PyTorch's and lerobot's (about 10 s of CPU on 2 cores, of
the 39 a minimal two-round simulation took) for a ServerApp, every run. zk0's SuperExec
(``python -m zk0.deployment.superexec``) keeps a fork server: a process that imported those
once and forks a child per task, which runs Flower's command with the arguments Flower chose
(its token, TLS, parent pid).

The child is still Flower's task process: it pulls the task, unpacks the submitted FAB and
imports the app's code from it. The fork server holds only third-party modules and no ``zk0``
module a child could reuse (each child forgets them before Flower loads the app), so the code
that runs is the submitted app's, and the app fingerprint check sees it. The fork server starts
no thread of its own (a library it imports may start a helper thread, such as jemalloc's
background thread, which registers its own fork handlers), so forking it is safe; a child resets
the signals and output the fork server changed.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import sys
import warnings
from typing import IO

from loguru import logger

# What a zk0 ServerApp imports that takes seconds, loaded once by a SuperLink's fork server: only
# third-party modules (the app's own come from the FAB). Neither MuJoCo (it chooses its GL
# backend from MUJOCO_GL when imported) nor Ray (a run's process starts its own).
SERVER_LIBRARIES = (
    "torch",
    "lerobot.datasets.lerobot_dataset",
    "lerobot.datasets.factory",
    "lerobot.policies.factory",
    "lerobot.processor",
    "matplotlib.figure",
)


class ForkServer:
    """The SuperExec's side: start the fork server once, then hand it each task's arguments. A
    SuperNode's serves ClientApps; a SuperLink's (``server``) serves ServerApps and simulations."""

    def __init__(self, server: bool = False) -> None:
        self.what = "ServerApp" if server else "ClientApp"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "zk0.deployment.forkserver", *(["--server"] if server else [])],
            stdin=subprocess.PIPE,
            text=True,
        )
        self.gone = False

    def start(self, args: list[str], quiet: bool) -> bool:
        """Ask for a process running ``args`` (``flwr-clientapp ...``, ``flwr-simulation ...``);
        False if the fork server is gone (the caller then starts the process as Flower would)."""
        if self.gone:
            return False
        try:
            self.process.stdin.write(json.dumps({"args": args, "quiet": quiet}) + "\n")
            self.process.stdin.flush()
            return True
        except OSError:  # a broken pipe: the fork server exited
            logger.warning(
                "zk0: the {} fork server exited (code {}); each {} process now starts afresh, as Flower starts it.",
                self.what,
                self.process.wait(),
                self.what,
            )
            self.gone = True
            return False


def serve(requests: IO[str], server: bool = False) -> None:
    """Import what Flower's task commands run (with ``server``, ServerApps' and simulations', and
    ``SERVER_LIBRARIES``), then fork a task for each request until the SuperExec closes the pipe
    (it exited, or was killed)."""
    from flwr.supernode.cli import flwr_clientapp

    from zk0 import internals

    commands = {"flwr-clientapp": flwr_clientapp}
    if server:
        from flwr.simulation.app import flwr_simulation
        from flwr.superlink.cli import flwr_serverapp

        commands |= {"flwr-serverapp": flwr_serverapp, "flwr-simulation": flwr_simulation}
        for name in SERVER_LIBRARIES:
            importlib.import_module(name)
    internals.shorten_object_pull_backoff()  # the arrays a task pulls from its SuperNode or SuperLink
    _forget_zk0()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group: the SuperExec ends this
    signal.signal(signal.SIGCHLD, _reap)
    for line in requests:
        request = json.loads(line)
        command = commands.get(request["args"][0])
        if command is None:
            logger.error("zk0: this fork server starts {}, not {!r}.", ", ".join(commands), request["args"][0])
            continue
        with warnings.catch_warnings():  # Python warns of any thread; see the module's docstring
            warnings.filterwarnings("ignore", "This process .* is multi-threaded", DeprecationWarning)
            child = os.fork()
        if child == 0:
            _run_task(command, request["args"], request["quiet"])


def _run_task(command, args: list[str], quiet: bool) -> None:
    """In the forked child: become Flower's ``args`` (``command`` is its entry point) as a fresh
    process would be, then exit."""
    code = 1
    try:
        for sig in (signal.SIGINT, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)  # the fork server's stdin is the SuperExec's pipe
        if quiet:
            os.dup2(null, 1)
            os.dup2(null, 2)
        os.close(null)
        sys.argv = args
        command()
        code = 0
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
    except BaseException:
        logger.exception("The forked {} process failed", args[0])
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _forget_zk0() -> None:
    """Drop the installed ``zk0`` modules (this module's package), so a child imports the app's
    code from the submitted FAB, where Flower points ``sys.path``, not from this process."""
    for name in [n for n in sys.modules if n == "zk0" or n.startswith("zk0.")]:
        del sys.modules[name]


def _reap(_signum: int, _frame: object) -> None:
    """Collect finished task processes (Flower never waits for them either)."""
    try:
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass
    except ChildProcessError:
        pass


if __name__ == "__main__":
    serve(sys.stdin, server="--server" in sys.argv[1:])
