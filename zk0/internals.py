"""Every private name of lerobot, PyTorch and Flower that zk0 touches, behind one door.

zk0 wraps these libraries through their public APIs, except in the few places below where
none exists. Each use is a small function here, and ``check()`` (run by
``tests/test_internals.py``) fails naming the installed versions when an upgrade removes or
reshapes one, instead of letting the frame cache or the LR schedule break quietly.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import subprocess
import time
from collections.abc import Callable
from functools import partial
from importlib.metadata import version
from typing import TYPE_CHECKING

from flwr.supercore import heartbeat
from flwr.supercore.constant import TASK_TYPE_TO_COMMAND, TaskType
from flwr.supercore.exit import add_exit_handler
from flwr.supercore.inflatable import inflatable_utils
from flwr.supercore.superexec.executor import subprocess_executor
from flwr.superlink.grid import InMemoryGrid
from flwr.supernode import fleet_http_connection
from flwr.supernode import start_client_internal as supernode_loop

if TYPE_CHECKING:  # lerobot and torch load where they are used: `python -m zk0.deployment.supernode` needs neither
    from lerobot.datasets.dataset_reader import DatasetReader
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from torch.optim.lr_scheduler import LRScheduler


def decode_videos(reader: DatasetReader, query_timestamps: dict[str, list[float]], episode: int) -> dict:
    """lerobot's own decoding of ``query_timestamps`` (camera -> timestamps) of one episode."""
    return type(reader)._query_videos(reader, query_timestamps, episode)


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


class _Waits:
    """The ``time`` module as Flower's SuperNode loop sees it, with its hard-coded sleeps replaced."""

    def __init__(self, waits: dict[float, float]):
        self.waits = waits

    def sleep(self, seconds: float) -> None:
        time.sleep(self.waits.get(seconds, seconds))

    def __getattr__(self, name: str):
        return getattr(time, name)


def shorten_supernode_waits(idle_s: float, reply_s: float) -> None:
    """Make this process's Flower SuperNode poll the SuperLink every ``idle_s`` when it has no
    message (Flower sleeps a hard-coded 3 s) and look for its ClientApp's reply every ``reply_s``
    (0.5 s). Neither has a flag or variable; the loop's module-level ``time`` is replaced."""
    supernode_loop.time = _Waits({3: idle_s, 0.5: reply_s})


def set_supernode_heartbeat(interval_s: float) -> None:
    """Make this process's SuperNode tell the SuperLink it beats every ``interval_s`` and beat that
    often; the SuperLink gives up on it after twice that. Flower's SuperNode hard-codes 30 s, so a
    robot that lost power held its round for a minute; no flag or variable sets it."""
    fleet_http_connection.HEARTBEAT_DEFAULT_INTERVAL = interval_s
    heartbeat.HEARTBEAT_DEFAULT_INTERVAL = interval_s


_PULLS = ("pull_objects", "pull_and_inflate_object_from_tree")
PULL_RETRY_S = 0.05  # zk0's first retry; it doubles up to Flower's cap (10 s), so long uploads cost few requests


def shorten_object_pull_backoff(initial_s: float = PULL_RETRY_S) -> None:
    """Make this process retry an object that is not there yet after ``initial_s`` (doubling up to
    Flower's cap), not Flower's hard-coded 1 s. A message is visible before its arrays are, so
    the SuperNode and its ClientApp each found them missing and waited a second, every message."""
    for name in _PULLS:
        getattr(inflatable_utils, name).__kwdefaults__["initial_backoff"] = initial_s


class _Starts:
    """The ``subprocess`` module as one of Flower's modules sees it, where ``start(args, kwargs)``
    may start a process named in ``names`` its own way (True) or leave it to ``subprocess.Popen``."""

    def __init__(self, names: set[str], start: Callable[[list[str], dict], bool]):
        self.names, self.start = names, start

    def Popen(self, args, **kwargs):  # noqa: N802 (subprocess's name)
        if args[0] in self.names and self.start(list(args), kwargs):
            return None  # Flower keeps no handle on the processes it starts here
        return subprocess.Popen(args, **kwargs)

    def __getattr__(self, name: str):
        return getattr(subprocess, name)


class _Renames:
    """The ``subprocess`` module as one of Flower's modules sees it, where the command ``name``
    runs as ``command`` (with Flower's arguments), and Flower keeps the process's handle."""

    def __init__(self, name: str, command: list[str]):
        self.name, self.command = name, command

    def Popen(self, args, **kwargs):  # noqa: N802 (subprocess's name)
        if args[0] == self.name:
            args = [*self.command, *args[1:]]
        return subprocess.Popen(args, **kwargs)

    def __getattr__(self, name: str):
        return getattr(subprocess, name)


def start_superexec_as(command: list[str]) -> None:
    """Make this process's SuperNode start ``command`` + Flower's arguments as its SuperExec,
    instead of ``flower-superexec`` (isolation ``subprocess``; no flag names the command)."""
    supernode_loop.subprocess = _Renames("flower-superexec", command)


def start_superlinks_superexec_as(command: list[str]) -> None:
    """Make this process's SuperLink start ``command`` + Flower's arguments as its SuperExec,
    instead of ``flower-superexec`` (isolation ``subprocess``; no flag names the command)."""
    _superlink_main().subprocess = _Renames("flower-superexec", command)


def _superlink_main():
    """``flwr.superlink.cli.flower_superlink``, the module (its package exports the function of
    the same name in its place), imported only where a SuperLink runs."""
    return importlib.import_module("flwr.superlink.cli.flower_superlink")


def start_tasks_with(task_types: list[TaskType], start: Callable[[list[str], bool], bool]) -> None:
    """Make this process's SuperExec hand each command of ``task_types`` (``flwr-clientapp``,
    ``flwr-serverapp``, ``flwr-simulation``: its whole command line) and whether Flower silences
    its output to ``start``, which returns False to leave it to ``subprocess.Popen``. Flower's
    subprocess executor has no hook for how a task's process starts."""

    def start_task(args: list[str], kwargs: dict) -> bool:
        return start(args, kwargs.get("stdout") is subprocess.DEVNULL)

    names = {TASK_TYPE_TO_COMMAND[task_type] for task_type in task_types}
    subprocess_executor.subprocess = _Starts(names, start_task)


# Ray's ``ray.init`` merges the job config in this variable (JSON; what ``ray job submit`` sets)
# into the runtime environment it is given: Flower's Ray backend passes its own to ``ray.init``,
# so this is the one way to add to it.
RAY_JOB_CONFIG = "RAY_JOB_CONFIG_JSON_ENV_VAR"


def start_ray_workers_with(command: str, env_vars: dict[str, str]) -> None:
    """Make this process's simulation start each Ray worker as ``command`` + Ray's worker script
    and arguments (Ray's ``py_executable``), with ``env_vars`` in its environment, in place of
    ``python``; a job config already set (a run under ``ray job submit``) is left alone."""
    os.environ.setdefault(RAY_JOB_CONFIG, json.dumps({"runtime_env": {"py_executable": command, "env_vars": env_vars}}))


def check() -> None:
    """Raise, naming the installed versions, if a private name above is gone or changed shape."""
    from lerobot.datasets.dataset_reader import DatasetReader
    from torch.optim.lr_scheduler import LRScheduler

    versions = f"lerobot {version('lerobot')}, torch {version('torch')}, flwr {version('flwr')}"
    problems = []
    query = getattr(DatasetReader, "_query_videos", None)
    if query is None or list(inspect.signature(query).parameters) != ["self", "query_timestamps", "ep_idx"]:
        problems.append("DatasetReader._query_videos(self, query_timestamps, ep_idx)")
    if "self._return_uint8 =" not in inspect.getsource(DatasetReader.__init__):
        problems.append("DatasetReader._return_uint8")
    if "_last_lr" not in inspect.getsource(LRScheduler.get_last_lr):
        problems.append("LRScheduler._last_lr behind get_last_lr()")
    loop = inspect.getsource(supernode_loop)
    if "\nimport time\n" not in loop or "time.sleep(3)" not in loop or "time.sleep(0.5)" not in loop:
        problems.append("flwr.supernode.start_client_internal's `import time`, time.sleep(3) and time.sleep(0.5)")
    beats = inspect.getsource(fleet_http_connection) + inspect.getsource(heartbeat)
    if beats.count("heartbeat_interval=HEARTBEAT_DEFAULT_INTERVAL") != 2 or "= HEARTBEAT_DEFAULT_INTERVAL -" not in beats:
        problems.append("flwr.supernode.fleet_http_connection's and flwr.supercore.heartbeat's HEARTBEAT_DEFAULT_INTERVAL")
    superexec = ("\nimport subprocess\n", 'command = ["flower-superexec"]', "subprocess.Popen(command)")
    if not all(part in loop for part in superexec):
        problems.append('flwr.supernode.start_client_internal\'s `subprocess.Popen(["flower-superexec", ...])`')
    link = inspect.getsource(_superlink_main())
    if not all(part in link for part in ("\nimport subprocess\n", 'command = ["flower-superexec"]',
                                         "subprocess.Popen(command, ")):  # fmt: skip
        problems.append('flwr.superlink.cli.flower_superlink\'s `subprocess.Popen(["flower-superexec", ...], ...)`')
    executor = inspect.getsource(subprocess_executor)
    if "\nimport subprocess\n" not in executor or "subprocess.Popen(args)" not in executor:
        problems.append("flwr.supercore.superexec.executor.subprocess_executor's `subprocess.Popen(args)`")
    commands = {TASK_TYPE_TO_COMMAND[t] for t in (TaskType.CLIENT_APP, TaskType.SERVER_APP, TaskType.SIMULATION)}
    if "stdout=subprocess.DEVNULL" not in executor or commands != {"flwr-clientapp", "flwr-serverapp", "flwr-simulation"}:
        problems.append("SubprocessExecutor starting `flwr-clientapp`, `flwr-serverapp` and `flwr-simulation` "
                        "(output to subprocess.DEVNULL when suppressed)")  # fmt: skip
    for name in _PULLS:
        defaults = getattr(getattr(inflatable_utils, name, None), "__kwdefaults__", None) or {}
        if "initial_backoff" not in defaults:
            problems.append(f"flwr.supercore.inflatable.inflatable_utils.{name}(..., *, initial_backoff=...)")
    problems += _check_ray()
    if "run_before_force_exit" not in inspect.signature(add_exit_handler).parameters:
        problems.append("flwr.supercore.exit.add_exit_handler(handler, run_before_force_exit=...)")
    if problems:
        raise RuntimeError(
            f"zk0 relies on {', '.join(problems)}, which {versions}, ray {version('ray')} no longer has; "
            "update zk0/internals.py."
        )


def _check_ray() -> list[str]:
    """What :func:`start_ray_workers_with` needs of Ray, where it is missing."""
    from ray._private import worker
    from ray._private.runtime_env import constants
    from ray._private.runtime_env.context import RuntimeEnvContext
    from ray.runtime_env import RuntimeEnv

    problems = []
    if getattr(constants, "RAY_JOB_CONFIG_JSON_ENV_VAR", None) != RAY_JOB_CONFIG or RAY_JOB_CONFIG not in inspect.getsource(worker.init):
        problems.append(f"ray.init merging the job config in ${RAY_JOB_CONFIG}")
    if "py_executable" not in RuntimeEnv.known_fields or '["exec", self.py_executable]' not in inspect.getsource(RuntimeEnvContext.exec_worker):
        problems.append("the runtime environment's py_executable, run as `exec <py_executable> <worker script> <args>`")
    return problems
