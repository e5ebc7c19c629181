"""A stopped run writes nothing more: Ctrl-C in ``./train.sh`` and ``flwr stop`` end it at once.

Flower stops a run by signalling the process its ServerApp runs in; the signal handler logs
"Task stopped by user", runs the process's exit handlers and ends the main thread. In a
simulation the ServerApp runs in another thread, which Flower lets go on until its force-exit
timer (5 s) ends the process: short rounds went on being written for seconds after the stop.
zk0 asks Flower to call it first when the process exits (``watch``); from then on the
ServerApp's writers refuse (``check`` raises ``RunStopped``), which also ends its round loop.
"""

from __future__ import annotations

import threading

from zk0.errors import Zk0Error
from zk0.internals import on_flower_exit

_stopped = threading.Event()
_watching = threading.Lock()


class RunStopped(Zk0Error):
    """The run was stopped (Ctrl-C, ``flwr stop``); nothing more is written."""


def watch() -> None:
    """Learn of this process's exit first, before Flower's slower exit handlers (once per process).

    ``flwr stop`` reaches the process through the SuperLink refusing the run's next request (a log
    upload, a heartbeat), on which Flower signals the process: the same exit, so the same handler."""
    if _watching.acquire(blocking=False):
        on_flower_exit(_stopped.set)


def check(server_round: int) -> None:
    """Raise ``RunStopped`` once the process is exiting: called before the ServerApp writes a file."""
    if _stopped.is_set():
        raise RunStopped(f"The run was stopped in round {server_round}; the server writes nothing more.")
