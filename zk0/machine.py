"""Sharing one machine's CPUs among the SuperNodes running on it.

Two SuperNodes on one machine, each letting PyTorch use every core, made each client's step
33x slower (their threads fight). ``zk0 supernode --cpus N`` fixes a SuperNode's share; without
it, the share follows the machine: every ``zk0 supernode`` registers its process id in a
per-user folder before it becomes Flower's SuperNode (the process id stays the same), and
before each message its client takes the CPUs this process may use divided by the SuperNodes
alive now (``cpus_now``). A SuperNode alone gets the whole machine; a second one started
beside it halves both from their next message on.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import psutil

SHARED = "ZK0_SUPERNODES"  # environment: the folder where this machine's SuperNodes register
FIXED = "ZK0_CPUS"  # environment: `zk0 supernode --cpus`


def registry_folder() -> Path:
    """Where this user's SuperNodes on this machine register."""
    return Path(tempfile.gettempdir()) / f"zk0-{os.getuid()}" / "supernodes"


def register(folder: Path, pid: int | None = None) -> None:
    """Count process ``pid`` (default: this one) among the SuperNodes sharing this machine."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / str(pid or os.getpid())).touch()


def alive(folder: Path) -> int:
    """SuperNodes registered in ``folder`` whose process still runs (the others' entries go)."""
    count = 0
    for entry in folder.glob("*"):
        if entry.name.isdigit() and psutil.pid_exists(int(entry.name)):
            count += 1
        else:
            entry.unlink(missing_ok=True)
    return count


def affinity() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0))


def cpus_now() -> int | None:
    """This SuperNode's CPUs: ``--cpus``, else its share of the machine now; None outside a SuperNode."""
    if os.environ.get(FIXED, "").isdigit():
        return int(os.environ[FIXED])
    if SHARED in os.environ:
        return max(1, affinity() // max(1, alive(Path(os.environ[SHARED]))))
    return None
