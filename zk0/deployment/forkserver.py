"""ClientApp processes forked from one that has already imported Flower, instead of started afresh.

Flower's SuperExec starts a new ``flwr-clientapp`` process for every message (both isolation
modes, flwr 1.41-1.43): Python's start and Flower's imports (FastAPI, SQLAlchemy, httpx, the
protobufs; about a second of CPU, two on a busy machine) before the message is even fetched,
every round. ``zk0 supernode``'s SuperExec (``python -m zk0.deployment.superexec``) keeps one fork server
per SuperNode: a process that imported ``flwr-clientapp``'s code once and forks a child per task,
which runs ``flwr-clientapp`` with the arguments Flower chose (its token, TLS, parent pid).

The child is still Flower's ClientApp process, one per message: it pulls the task, unpacks the
submitted FAB and imports the app's code from it. The fork server holds no ``zk0`` module a child
could reuse (each child forgets them before Flower loads the app), so the code that runs is the
submitted app's, and the app fingerprint check sees it. The fork server starts no thread, so
forking it is safe; a child resets the signals and output the fork server changed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from typing import IO

from loguru import logger


class ForkServer:
    """The SuperExec's side: start the fork server once, then hand it each ClientApp's arguments."""

    def __init__(self) -> None:
        self.process = subprocess.Popen([sys.executable, "-m", "zk0.deployment.forkserver"], stdin=subprocess.PIPE, text=True)
        self.gone = False

    def start(self, args: list[str], quiet: bool) -> bool:
        """Ask for a ClientApp process running ``args`` (``flwr-clientapp ...``); False if the
        fork server is gone (the caller then starts the process as Flower would)."""
        if self.gone:
            return False
        try:
            self.process.stdin.write(json.dumps({"args": args, "quiet": quiet}) + "\n")
            self.process.stdin.flush()
            return True
        except OSError:  # a broken pipe: the fork server exited
            logger.warning(
                "zk0: the ClientApp fork server exited (code {}); each message's ClientApp process now "
                "starts afresh, as Flower starts it.",
                self.process.wait(),
            )
            self.gone = True
            return False


def serve(requests: IO[str]) -> None:
    """Import what ``flwr-clientapp`` runs, then fork a ClientApp for each request until the
    SuperExec closes the pipe (it exited, or was killed)."""
    from flwr.supernode.cli import flwr_clientapp

    from zk0 import internals

    internals.shorten_object_pull_backoff()  # the arrays a ClientApp pulls from its SuperNode
    _forget_zk0()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group: the SuperExec ends this
    signal.signal(signal.SIGCHLD, _reap)
    for line in requests:
        request = json.loads(line)
        if os.fork() == 0:
            _run_clientapp(flwr_clientapp, request["args"], request["quiet"])


def _run_clientapp(flwr_clientapp, args: list[str], quiet: bool) -> None:
    """In the forked child: become ``flwr-clientapp args`` as a fresh process would be, then exit."""
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
        flwr_clientapp()
        code = 0
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
    except BaseException:
        logger.exception("The forked ClientApp process failed")
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
    """Collect finished ClientApp processes (Flower never waits for them either)."""
    try:
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass
    except ChildProcessError:
        pass


if __name__ == "__main__":
    serve(sys.stdin)
