"""Sharing one machine's CPUs among the SuperNodes running on it.

Two SuperNodes on one machine, each letting PyTorch use every core, made each client's step
33x slower (their threads fight). ``zk0 supernode --cpus N`` fixes a SuperNode's share; without
it, the share follows the machine: every ``zk0 supernode`` registers its process id in a
per-user folder before it becomes Flower's SuperNode (the process id stays the same), and
before each message its client takes the CPUs this process may use divided by the SuperNodes
alive now (``cpus_now``). A SuperNode alone gets the whole machine; a second one started
beside it halves both from their next message on.

Real-time priority is the other way one process takes a machine: ``ordinary_scheduling`` keeps
the video encoder from leaving it behind.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil

from zk0.common.errors import Zk0Error

SHARED = "ZK0_SUPERNODES"  # environment: the folder where this machine's SuperNodes register
FIXED = "ZK0_CPUS"  # environment: `zk0 supernode --cpus`


def private_folder() -> Path:
    """This user's folder in the temporary directory (``<tmp>/zk0-<uid>``), mode 0700.

    The warm workers' sockets live here, so only this user may enter it. Whoever gets here
    first creates it (a SuperNode registering, or a worker starting): ``mkdir(parents=True)``
    of a folder below it would give it the default mode 0755, and that order is exactly what a
    fresh machine has. A folder of this user's that others may only read is tightened; one of
    another user's, a link, or one others may write in (they could have put a socket there)
    is refused in one sentence.
    """
    folder = Path(tempfile.gettempdir()) / f"zk0-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700)
    except FileExistsError:
        pass
    info = folder.lstat()
    if stat.S_ISLNK(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o022:
        raise Zk0Error(
            f"{folder} is not a private folder of this user (a link, another user's, or writable by others); "
            "remove it or set TMPDIR to a folder of your own."
        )
    if stat.S_IMODE(info.st_mode) != 0o700:
        folder.chmod(0o700)
    return folder


def registry_folder() -> Path:
    """Where this user's SuperNodes on this machine register."""
    return private_folder() / "supernodes"


def register(folder: Path, pid: int | None = None) -> None:
    """Count process ``pid`` (default: this one) among the SuperNodes sharing this machine."""
    folder.mkdir(exist_ok=True)
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


@contextmanager
def ordinary_scheduling() -> Iterator[None]:
    """The block, then this thread's scheduling policy as it was before it.

    SVT-AV1 (``libsvtav1``, lerobot's video codec), run as root, switches the thread that opens an
    encoder to real-time ``SCHED_FIFO`` priority 99 and leaves it there. Every process that thread
    starts afterwards inherits it: a benchmark that recorded its demonstrations and then started a
    federation ran the SuperLink, the server and Ray's actors at real-time priority, and the
    pytest run beside it got 2% of the CPU (2026-12-07). So zk0 wraps each episode it encodes."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        if os.sched_getscheduler(0) != policy:
            os.sched_setscheduler(0, policy, param)
