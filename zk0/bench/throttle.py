"""An honest slow owner: one SuperNode's processes held to a share of the CPU, as cpulimit does.

A federation of mixed hardware needs, in tests and benchmarks, an owner whose machine really is
slower, not a sleep in zk0's code. ``Throttle`` duty-cycles every process working in one
SuperNode's folder with SIGSTOP and SIGCONT (what Debian's ``cpulimit`` does to one process): in
every period of 0.1 s they run for ``share`` of it and are stopped for the rest, so whatever they
compute takes about 1 / ``share`` times as long. The processes are found again every period by
their working folder, which the SuperNode's SuperExec, its per-message ClientApp processes and
its warm worker all inherit (the worker starts a session of its own, so its process group would
miss it). Every process is continued when the throttle ends, whatever happened.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path

import psutil

PERIOD_S = 0.1


def working_in(folder: Path) -> list[int]:
    """This user's processes whose working folder is ``folder`` or below it."""
    found = []
    for proc in psutil.process_iter(["pid", "cwd", "uids"]):
        cwd, uids = proc.info.get("cwd"), proc.info.get("uids")
        if cwd and uids and uids.real == os.getuid() and Path(cwd).is_relative_to(folder):
            found.append(proc.info["pid"])
    return found


class Throttle:
    """Hold the processes working in ``folder`` to ``share`` (0-1] of the time, while in ``with``."""

    def __init__(self, folder: Path, share: float, period_s: float = PERIOD_S) -> None:
        if not 0 < share <= 1:
            raise ValueError(f"A throttle's share of the CPU must be in (0, 1], got {share}.")
        self.folder, self.share, self.period_s = folder.resolve(), share, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._cycle, name=f"throttle {folder.name}", daemon=True)
        self._stopped: set[int] = set()

    def __enter__(self) -> Throttle:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._signal(self._stopped, signal.SIGCONT)

    def _signal(self, pids, sig: int) -> None:
        for pid in list(pids):
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)

    def _cycle(self) -> None:
        """Run for ``share`` of each period, stopped for the rest, until the ``with`` ends."""
        running = self.share * self.period_s
        while not self._stop.is_set():
            self._signal(self._stopped, signal.SIGCONT)
            self._stopped.clear()
            started = time.monotonic()
            pids = working_in(self.folder)  # found while they run: a new worker is caught in its first period
            self._stop.wait(max(0.0, running - (time.monotonic() - started)))
            if self._stop.is_set() or self.share == 1:
                continue
            self._signal(pids, signal.SIGSTOP)
            self._stopped = set(pids)
            self._stop.wait(self.period_s - running)
