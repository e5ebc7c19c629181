"""What a federation's processes hold while it runs: the scale and soak benchmarks' eyes.

``Watch.during(env)`` samples every process under a simulation's SuperLink every half second:
resident memory by role (the SuperLink, its SuperExec, the simulation process that runs the
ServerApp and holds the SuperNodes, each Ray actor running ClientApps, Ray's own daemons).
``Watch.around(processes)`` does the same for a Deployment Engine federation's process trees
(the SuperLink with its ServerApp process, each SuperNode with its warm worker). At the end of
every round (when its ``server/round_<N>.json`` appears) it keeps a row of that moment: memory by
role and of each client process, open file descriptors and threads of the server side and the
clients, and the size of the run's output folder.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil

from zk0.deployment.forkserver import RAY_WORKER_SERVER
from zk0.deployment.simulation import superlink_tree

MIB = 2**20
# What each process of a federation is, by a word in its command line (the first that matches).
# In simulation flwr-simulation runs the ServerApp and the Simulation Engine, which holds the N
# SuperNodes, and Ray's actors run the ClientApps. In a deployment flwr-serverapp runs the ServerApp
# and each SuperNode's warm worker (zk0.deployment.worker) keeps its client; a SuperNode's own processes (its
# SuperExec, fork server and the ClientApp process relaying each message) are "supernode". zk0's
# SuperLink forks each run's flwr-simulation (or flwr-serverapp) from its SuperExec's fork server,
# whose command line the child shows: the fork server itself ("fork server") holds the libraries the
# child shares, so it is left out of the server side, which counts them in the child; so is the
# Ray worker fork server beside it (named RAY_WORKER_SERVER), whose forked workers name themselves
# ``ray::ClientAppActor`` once Ray starts in them.
FORK_SERVER = "zk0.deployment.forkserver --server"
ROLES = {
    "ClientAppActor": "client",
    "zk0.deployment.worker": "client",
    "flwr-simulation": "simulation",
    "flwr-serverapp": "serverapp",
    "zk0.deployment.supernode": "supernode",
    "zk0.deployment.superexec --server": "superexec",
    "zk0.deployment.superexec": "supernode",
    "zk0.deployment.forkserver": "supernode",
    "flwr-clientapp": "supernode",
    "flower-superexec": "superexec",
    "flower-superlink": "superlink",
    "zk0.deployment.superlink": "superlink",
}
SERVER_SIDE = ("superlink", "superexec", "simulation", "serverapp")


def role_of(process: psutil.Process) -> str:
    """A process's part in the federation (``ray`` for Ray's own daemons and workers, ``other`` for
    what is none of these, such as the ``zk0`` command that started a SuperLink or SuperNode)."""
    cmdline = " ".join(process.cmdline())
    if FORK_SERVER in cmdline:
        parent = process.parent()
        if process.name() == RAY_WORKER_SERVER or parent is None or FORK_SERVER not in " ".join(parent.cmdline()):
            return "fork server"
        simulating = any("--simulation" in " ".join(p.cmdline()) for p in process.parents())
        return "simulation" if simulating else "serverapp"  # a run's process, forked
    return next((role for word, role in ROLES.items() if word in cmdline), "ray" if "ray" in cmdline else "other")


def folder_bytes(folder: Path) -> int:
    """What the files under ``folder`` take (a file removed while counting is skipped)."""
    total = 0
    for path in folder.rglob("*"):
        try:
            total += path.stat().st_size if path.is_file() else 0
        except OSError:
            continue
    return total


class Watch:
    """Samples the federation's processes every ``period_s``; a row at the end of every round."""

    def __init__(self, output_dir: Path, period_s: float = 0.5) -> None:
        self.output_dir, self.period_s = output_dir, period_s
        self.peak_mib: dict[str, float] = {}  # role -> largest resident set of one sample (summed over its processes)
        self.client_process_mib = 0.0  # the largest single client process
        self.recorded_at: dict[int, float] = {}  # round -> seconds after the run started
        self.rounds: list[dict] = []  # a row at each round's end
        self.started = time.perf_counter()
        self._stop = threading.Event()

    def during(self, env: dict[str, str]):
        """Watch the simulation whose SuperLink runs with ``env`` (``run_federation``'s ``watch``)."""
        return self.around(lambda: superlink_tree(env))

    @contextmanager
    def around(self, processes: Callable[[], list[psutil.Process]]) -> Iterator[None]:
        """Watch what ``processes()`` lists at each sample (the federation's processes now)."""
        self.started = time.perf_counter()
        thread = threading.Thread(target=self._sample, args=(processes,), daemon=True)
        thread.start()
        try:
            yield
        finally:
            self._stop.set()
            thread.join()

    def _sample(self, listed: Callable[[], list[psutil.Process]]) -> None:
        while not self._stop.wait(self.period_s):
            processes = []
            for process in listed():
                try:
                    with process.oneshot():
                        processes.append(
                            (role_of(process), process.pid, process.memory_info().rss / MIB,
                             process.num_fds(), process.num_threads())
                        )  # fmt: skip
                except psutil.Error:  # ended between the listing and the reading
                    continue
            totals: dict[str, float] = {}
            for role, _, rss, _, _ in processes:
                totals[role] = totals.get(role, 0.0) + rss
            totals["server side"] = sum(totals.get(r, 0.0) for r in SERVER_SIDE)
            for role, total in totals.items():
                self.peak_mib[role] = max(self.peak_mib.get(role, 0.0), total)
            clients = {pid: rss for role, pid, rss, _, _ in processes if role == "client"}
            self.client_process_mib = max(self.client_process_mib, *clients.values(), 0.0)
            self._note_rounds(totals, clients, processes)

    def _note_rounds(self, totals: dict[str, float], clients: dict[int, float], processes: list[tuple]) -> None:
        """A row for each round whose JSON has appeared since the last sample."""
        done = {int(p.stem.removeprefix("round_")) for p in self.output_dir.glob("*/server/round_*.json")}
        new = sorted(done - set(self.recorded_at))
        if not new:
            return
        now = time.perf_counter() - self.started
        size = sum(folder_bytes(run) for run in self.output_dir.iterdir() if run.is_dir())
        for number in new:
            self.recorded_at[number] = now
            self.rounds.append({
                "round": number, "s": now, "mib": dict(totals), "client-processes-mib": {str(p): m for p, m in clients.items()},
                "server-fds": sum(f for role, _, _, f, _ in processes if role in SERVER_SIDE),
                "server-threads": sum(t for role, _, _, _, t in processes if role in SERVER_SIDE),
                "client-fds": sum(f for role, _, _, f, _ in processes if role == "client"),
                "client-threads": sum(t for role, _, _, _, t in processes if role == "client"),
                "output-bytes": size,
            })  # fmt: skip
