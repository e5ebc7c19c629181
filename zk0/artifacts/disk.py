"""Will the run fit on the disk? Checked before round 1, so a run does not die of a full disk on day three;
and if the disk fills anyway (another program, a frame cache), one sentence instead of a traceback.

A full-size checkpoint is 1.8 GB; a run writes one every ``checkpoint-interval`` rounds and keeps
the newest ``keep-checkpoints`` (one more while the next is being written, before the oldest
goes), ``models/best`` beside them, and a few small files a round (its JSON, the charts, with
closed-loop evaluation a video). The estimate is what the run still has to write from here; the
ServerApp refuses in one sentence, naming the folder, what the run needs and what is free, when it
cannot fit, and warns when it fills the disk to within a tenth. A disk that fills mid-run ends the
run (or the client's message) with ``full_disk_in_one_sentence``'s sentence, naming the folder and
its free space; every file zk0 writes is renamed into place once complete, so none is left half
written where a reader or a resumed run would take it.
"""

from __future__ import annotations

import errno
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from loguru import logger

from zk0.common.errors import Zk0Error
from zk0.config import RunConfig
from zk0.learning.policy import PolicyBundle

PER_ROUND_BYTES = 2 * 2**20  # a round's JSON files, the rewritten charts and report, a closed-loop video
GB = 1e9


def checkpoint_bytes(bundle: PolicyBundle) -> int:
    """One checkpoint's size: the policy's weights, and the server optimiser's state (at most two
    fp32 moments of every trainable tensor: FedAdam's)."""
    state = bundle.policy.state_dict()
    weights = sum(t.numel() * t.element_size() for t in state.values())
    return weights + 2 * 4 * sum(state[name].numel() for name in bundle.trainable_names if name in state)


def checkpoints_on_disk(run: RunConfig, first_round: int) -> int:
    """How many checkpoints rounds ``first_round``.. of the run have on disk at once, at most."""
    written = sum(run.checkpoints_in(r) for r in range(first_round, run.num_server_rounds + 1))
    return min(written, run.keep_checkpoints + 1) if run.keep_checkpoints else written


def bytes_needed(run: RunConfig, first_round: int, checkpoint_bytes: int) -> int:
    """What the run writes from round ``first_round`` on: its checkpoints, models/best, per-round files."""
    rounds = run.num_server_rounds - first_round + 1
    return (checkpoints_on_disk(run, first_round) + 1) * checkpoint_bytes + rounds * PER_ROUND_BYTES


def size(count: int) -> str:
    """``1.8 GB``, or ``21 MB`` below a tenth of a gigabyte."""
    return f"{count / GB:.1f} GB" if count >= 0.1 * GB else f"{count / 1e6:.0f} MB"


def check_room(folder: Path, needed: int) -> None:
    """Refuse (a ``Zk0Error``) when ``needed`` bytes do not fit in ``folder``'s free space; warn
    when they leave less than a tenth of it."""
    free = shutil.disk_usage(folder).free
    said = f"{str(folder)!r} needs about {size(needed)} for this run's checkpoints, models/best and round files"
    if needed > free:
        raise Zk0Error(
            f"{said}, but only {size(free)} is free there; free some space, pick another output-dir "
            "or lower keep-checkpoints."
        )
    if needed > 0.9 * free:
        logger.warning(
            "{}, which leaves {} of the {} free there: the disk will be nearly full.",
            said,
            size(free - needed),
            size(free),
        )


def is_full(err: BaseException) -> bool:
    """Whether ``err`` says a disk is full: an ``OSError`` with ENOSPC, or a library's error that
    wraps one (safetensors: "I/O error: No space left on device (os error 28)")."""
    return (isinstance(err, OSError) and err.errno == errno.ENOSPC) or "No space left on device" in str(err)


def _existing(path: Path) -> Path:
    """``path`` or its nearest folder that exists (a file a full disk kept from being written may not)."""
    while not path.is_dir() and path != path.parent:
        path = path.parent
    return path


@contextmanager
def full_disk_in_one_sentence(where: Path, then: str) -> Iterator[None]:
    """A full disk inside the ``with`` becomes a ``Zk0Error``: the folder (the file's, when the error
    names one, else ``where``), its free space, and ``then``, what to do about it."""
    try:
        yield
    except Zk0Error:
        raise
    except Exception as err:
        if not is_full(err):
            raise
        folder = _existing(Path(err.filename) if isinstance(err, OSError) and err.filename else where)
        free = shutil.disk_usage(folder).free
        raise Zk0Error(f"The disk holding {str(folder)!r} is full ({size(free)} free); {then}") from None
