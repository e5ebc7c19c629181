"""Shared fixtures: an isolated asset cache, offline Hub, and the tiny policy on a client dataset."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.allowances import pytest_collection_modifyitems, pytest_runtest_makereport  # noqa: F401 (pytest's hooks)

REPO = Path(__file__).resolve().parents[1]
# One cache for the whole test session, shared by xdist workers (generation is locked).
os.environ.setdefault("ZK0_CACHE", str(REPO / ".cache" / "zk0-tests"))
os.environ["HF_HUB_OFFLINE"] = "1"
# `-n auto` runs one xdist worker per core: one thread each, and in the processes they start
# (the federations' servers and clients), or PyTorch's thread pools oversubscribe the cores.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("SVT_LOG", "1")


def require_tool(command: str, package: str) -> None:
    """Skip a test that needs Debian's ``package`` for ``command`` where it is missing, except in CI
    on a machine where ``./test.sh`` installs it (root with apt-get): there its absence is a fault."""
    if shutil.which(command):
        return
    message = f"{command} is not installed (apt-get install {package})"
    if os.environ.get("CI") and os.getuid() == 0 and shutil.which("apt-get"):
        pytest.fail(f"{message}, though ./test.sh installs it on this machine (root with apt-get)")
    pytest.skip(message)


@pytest.fixture(autouse=True)
def ordinary_scheduling():
    """Each test (and what it starts) under the ordinary time-sharing policy, as a user's processes
    run, and its worker left so. In clean-clone CI runs both test workers were found at SCHED_FIFO
    99 part-way through the suite: lerobot's video codec (libsvtav1), run as root, leaves the
    thread that encoded a video there (tests/test_assets.py), and tests write datasets with
    lerobot's own calls. Busy processes a test started inherited it, held both cores and starved
    the other worker (tests/test_throttle.py hung); the next test's session fixtures (this
    worker's SuperLink) start before this fixture, so it also resets when a test ends."""
    from zk0.common import machine

    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with machine.ordinary_scheduling():
        yield


@pytest.fixture(scope="session", autouse=True)
def offline_assets():
    """The offline backbone and datasets, generated once (opening a registry entry never does)."""
    from zk0.data.assets import ensure_all

    ensure_all()


@pytest.fixture(scope="session")
def flower_env():
    """The private local simulation SuperLink of this test worker, which the benchmarks' federations
    run on too (zk0.deployment.simulation.process_superlink): a SuperLink's start is seconds of every
    federation otherwise."""
    from zk0.deployment.simulation import process_superlink

    env = process_superlink()
    env.pop("HF_TOKEN", None)  # the Hub push stays offline: staged, not uploaded
    return env


@pytest.fixture(scope="session")
def registry():
    from zk0.data.registry import load_registry

    return load_registry()


@pytest.fixture
def run_config():
    from zk0.config import from_run_config

    return from_run_config({"batch-size": 4, "lr": 1e-3, "local-steps": 5})


@pytest.fixture
def client_parts(registry, run_config):
    """Policy bundle, dataset split and trainer for client 0, built the way the ClientApp builds them."""
    from zk0.federation.client import build_client

    client = build_client(run_config, registry.clients[0], registry.model_cameras())
    return client.bundle, client.split, client.trainer


@pytest.fixture
def flower_task():
    """Flower's runtime sets who is sending a Message; here the test plays task 1 of run 1 on node 0,
    and Flower's class state is put back afterwards."""
    from flwr.supercore.task_identity import TaskIdentity

    saved = TaskIdentity._run_id, TaskIdentity._task_id, TaskIdentity._node_id
    TaskIdentity.run_id, TaskIdentity.task_id, TaskIdentity.node_id = 1, 1, 0
    yield
    TaskIdentity._run_id, TaskIdentity._task_id, TaskIdentity._node_id = saved


@pytest.fixture
def isolated_logging():
    """For a test whose code calls ``zk0.artifacts.logs.setup_logging`` (directly or by handling a message):
    the standard-library logging it rewires is put back, and loguru is left as a fresh process
    has it, so later tests see the logging they would alone."""
    import logging
    import sys

    from loguru import logger

    from zk0.artifacts import logs

    names = ["", "flwr", "lerobot", "ray", "accelerate", "httpx", "httpcore", "urllib3", "filelock"]
    saved = {name: (logging.getLogger(name), logging.getLogger(name).handlers[:]) for name in names}
    levels = {name: (lg.level, lg.propagate) for name, (lg, _) in saved.items()}
    yield
    for name, (lg, handlers) in saved.items():
        lg.handlers = handlers
        lg.setLevel(levels[name][0])
        lg.propagate = levels[name][1]
    logger.remove()
    logger.configure(extra={})
    logger.add(sys.stderr)
    logs._console_sink = None  # the next setup_logging starts from loguru's defaults again
