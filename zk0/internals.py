"""Every private name of lerobot, PyTorch and Flower that zk0 touches, behind one door.

zk0 wraps these libraries through their public APIs, except in the few places below where
none exists. Each use is a small function here, and ``check()`` (run by
``tests/test_internals.py``) fails naming the installed versions when an upgrade removes or
reshapes one, instead of letting the frame cache or the LR schedule break quietly.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from functools import partial
from importlib.metadata import version

from flwr.supercore.exit import add_exit_handler
from flwr.superlink.grid import InMemoryGrid
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from torch.optim.lr_scheduler import LRScheduler


def decode_videos(reader: DatasetReader, query_timestamps: dict[str, list[float]], episode: int) -> dict:
    """lerobot's own decoding of ``query_timestamps`` (camera -> timestamps) of one episode."""
    return DatasetReader._query_videos(reader, query_timestamps, episode)


def serve_videos_from(dataset: LeRobotDataset, query: Callable[[DatasetReader, dict, int], dict]) -> None:
    """Make ``dataset`` answer its video queries with ``query(reader, query_timestamps, episode)``:
    lerobot has no hook for where frames come from, so the reader's method is replaced."""
    dataset.reader._query_videos = partial(query, dataset.reader)


def video_query(dataset: LeRobotDataset) -> Callable[[dict, int], dict]:
    """What ``dataset`` answers its video queries with (lerobot's decoder, or the frame cache's)."""
    return dataset.reader._query_videos


def returns_uint8(dataset: LeRobotDataset) -> bool:
    """Whether ``dataset`` hands frames out as uint8 (lerobot's training path) or float in [0, 1]."""
    return dataset.reader._return_uint8


def set_last_lr(scheduler: LRScheduler, lrs: list[float]) -> None:
    """What ``scheduler.get_last_lr()`` reports after zk0 moves a schedule to a global step."""
    scheduler._last_lr = lrs


def is_simulation(grid: object) -> bool:
    """Whether a ServerApp runs in Flower's simulation (every SuperNode on this machine)."""
    return isinstance(grid, InMemoryGrid)


def on_flower_exit(handler: Callable[[], None]) -> None:
    """Call ``handler`` as soon as Flower ends this process (a stopped run's signal, or the end of
    the run), before its other exit handlers and its force-exit timer; Flower's ``add_exit_handler``
    is not part of its public API (``flwr.supercore``)."""
    add_exit_handler(handler, run_before_force_exit=True)


def check() -> None:
    """Raise, naming the installed versions, if a private name above is gone or changed shape."""
    versions = f"lerobot {version('lerobot')}, torch {version('torch')}, flwr {version('flwr')}"
    problems = []
    query = getattr(DatasetReader, "_query_videos", None)
    if query is None or list(inspect.signature(query).parameters) != ["self", "query_timestamps", "ep_idx"]:
        problems.append("DatasetReader._query_videos(self, query_timestamps, ep_idx)")
    if "self._return_uint8 =" not in inspect.getsource(DatasetReader.__init__):
        problems.append("DatasetReader._return_uint8")
    if "_last_lr" not in inspect.getsource(LRScheduler.get_last_lr):
        problems.append("LRScheduler._last_lr behind get_last_lr()")
    if "run_before_force_exit" not in inspect.signature(add_exit_handler).parameters:
        problems.append("flwr.supercore.exit.add_exit_handler(handler, run_before_force_exit=...)")
    if problems:
        raise RuntimeError(
            f"zk0 relies on {', '.join(problems)}, which {versions} no longer has; update zk0/internals.py."
        )
