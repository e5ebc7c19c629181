"""A stopped run writes nothing more: Ctrl-C in ``./train.sh`` and ``flwr stop`` end it at once.

Flower stops a run by signalling the process its ServerApp runs in; the signal handler logs
"Task stopped by user", runs the process's exit handlers and ends the main thread. In a
simulation the ServerApp runs in another thread, which Flower lets go on until its force-exit
timer (5 s) ends the process: short rounds went on being written for seconds after the stop.
zk0 asks Flower to call it first when the process exits (``watching``); from then on the
ServerApp's writers refuse (``check`` raises ``RunStopped``), which also ends its round loop.
The handler says so itself: the round loop may be in a step longer than the timer (a server
evaluation on a busy machine) and never reach a writer before the process ends.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from loguru import logger

from zk0.common.errors import Zk0Error
from zk0.internals import on_flower_exit

STOPPED = "The run was stopped; the server writes nothing more."

_stopped = threading.Event()
_running = threading.Event()
_said = threading.Event()
_registered = threading.Lock()


class RunStopped(Zk0Error):
    """The run was stopped (Ctrl-C, ``flwr stop``); nothing more is written."""


@contextmanager
def watching() -> Iterator[None]:
    """Around the ServerApp's round loop: learn of this process's exit first, before Flower's
    slower exit handlers, and say it was a stop only while the loop runs (Flower calls the same
    handlers when a finished run's process exits).

    ``flwr stop`` reaches the process through the SuperLink refusing the run's next request (a log
    upload, a heartbeat), on which Flower signals the process: the same exit, so the same handler."""
    if _registered.acquire(blocking=False):
        on_flower_exit(_on_exit)
    _running.set()
    try:
        yield
    except RunStopped:
        if not _said.is_set():  # the handler could not log (it interrupted a log call)
            logger.warning(STOPPED)
        raise
    finally:
        _running.clear()


def _on_exit() -> None:
    _stopped.set()
    if _running.is_set():
        logger.warning(STOPPED)
        _said.set()


def check(server_round: int) -> None:
    """Raise ``RunStopped`` once the process is exiting: called before the ServerApp writes a file."""
    if _stopped.is_set():
        raise RunStopped(f"The run was stopped in round {server_round}.")
