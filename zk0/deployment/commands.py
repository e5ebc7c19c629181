"""The Deployment Engine commands for a zk0 federation: one SuperLink, one SuperNode per robot owner.

These build Flower's SuperLink and SuperNode command lines (TLS and
SuperNode authentication on by default; ``insecure`` only when asked, with a warning)
that ``zk0 superlink`` / ``zk0 supernode`` run, so the documented commands and the tested
ones are the same. The apps are the simulation's: each SuperNode picks its dataset from the
registry through its node config, writes its client's log under its own output folder, and
keeps its client built in a warm worker (``zk0.deployment.worker``) between messages.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from loguru import logger

from zk0.common import machine
from zk0.common.errors import Zk0Error

INSECURE_WARNING = (
    "Running WITHOUT TLS: traffic is unencrypted and any SuperNode can join. Use only on a trusted test network."
)


def _need(path: Path, what: str) -> str:
    if not path.is_file():
        raise Zk0Error(f"{what} {str(path)!r} does not exist; create it with `zk0 certs`.")
    return str(path)


def superlink_command(certs: Path | None, host: str, port: int, database: Path | None) -> list[str]:
    """Flower's SuperLink with TLS and SuperNode authentication (``certs`` None = insecure), started
    as ``python -m zk0.deployment.superlink``: ``flower-superlink`` whose SuperExec forks each run's
    ServerApp process from one that has imported PyTorch and lerobot (about 10 s of CPU a run).

    flwr 1.42 serves the Fleet API (SuperNodes), the Control API (``flwr`` CLI) and the
    ServerApp runtime API over HTTPS on one ``host:port``.
    """
    command = [sys.executable, "-m", "zk0.deployment.superlink"]
    if certs is None:
        logger.warning(INSECURE_WARNING)
        command.append("--insecure")
    else:
        command += [
            "--ssl-ca-certfile", _need(certs / "ca.crt", "CA certificate"),
            "--ssl-certfile", _need(certs / "server.pem", "SuperLink certificate"),
            "--ssl-keyfile", _need(certs / "server.key", "SuperLink key"),
            "--enable-supernode-auth",
        ]  # fmt: skip
    command += ["--host", host, "--port", str(port), "--disable-runtime-dependency-installation"]
    if database is not None:
        command += ["--database", str(database)]
    return command


def node_config(dataset: str, output_dir: Path, warm_worker: bool) -> str:
    """The SuperNode's node config: the owner's dataset, where their client writes, the warm worker."""
    for name, value in (("--dataset", dataset), ("--output-dir", str(output_dir))):
        if "'" in value:
            raise Zk0Error(f"{name} got {value!r}; expected a value without single quotes.")
    return f"dataset='{dataset}' output-dir='{output_dir}' warm-worker={str(warm_worker).lower()}"


def supernode_command(
    superlink: str, certs: Path | None, key: str | None, node_config: str, runtime_port: int
) -> list[str]:
    """Flower's SuperNode for one robot owner (their node config, their key, the federation's CA),
    started as ``python -m zk0.deployment.supernode``: ``flower-supernode`` with shorter polls (zk0.deployment.supernode)."""
    command = [sys.executable, "-m", "zk0.deployment.supernode", "--superlink", superlink]
    if certs is None:
        logger.warning(INSECURE_WARNING)
        command.append("--insecure")
    else:
        if not key:
            raise Zk0Error("A secure SuperNode needs --key <name> (its key pair from `zk0 certs`).")
        command += [
            "--root-certificates", _need(certs / "ca.crt", "CA certificate"),
            "--auth-supernode-private-key", _need(certs / "supernodes" / key, "SuperNode private key"),
        ]  # fmt: skip
    command += [
        "--node-config", node_config,
        "--host", "127.0.0.1",
        "--port", str(runtime_port),
    ]  # fmt: skip
    return command


def thread_env(cpus: int | None, registry: Path) -> dict[str, str]:
    """Thread limits for everything a SuperNode starts (ClientApp processes, the warm worker).

    Ray sets these for simulated clients; nothing does on a SuperNode, and two SuperNodes on one
    machine, each using every core, made PyTorch's steps 33x slower. With ``cpus`` (``--cpus``)
    the share is fixed (``ZK0_CPUS``); without, the SuperNode registers in ``registry``
    (``zk0 supernode`` does, before it becomes the SuperNode) and its client takes its share of
    the machine before every message (zk0.common.machine). The share also sizes
    the DataLoader workers (``num-workers = -1``).
    """
    if cpus is None:  # the SuperNode about to start counts too
        cpus = machine.affinity() // (machine.alive(registry) + 1)
        limits = {machine.SHARED: str(registry)}
    else:
        limits = {machine.FIXED: str(cpus)}
    value = str(max(1, cpus))  # at start; the client sets PyTorch's threads again per message
    return {**limits, "OMP_NUM_THREADS": value, "MKL_NUM_THREADS": value}


# Flower's SuperExec looks for a new ClientApp task every second by default; every message waits
# for that poll, so a SuperNode started by zk0 looks ten times a second (a local SQLite query).
SUPEREXEC_POLL = {"FLWR_SUPEREXEC_TASK_POLL_INTERVAL": "0.1"}


def run(command: list[str], env: dict[str, str] | None = None) -> None:
    """Replace this process with ``command`` (signals and exit code are Flower's own)."""
    logger.info("Running: {}", " ".join(command))
    env = {**os.environ, **(env or {}), "FLWR_DISABLE_RUNTIME_DEPENDENCY_INSTALLATION": "1"}
    os.execvpe(command[0], command, env)
