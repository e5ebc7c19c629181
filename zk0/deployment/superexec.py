"""Flower's SuperExec, starting task processes from a fork server: ``python -m zk0.deployment.superexec``
takes ``flower-superexec``'s arguments (and ``--server``, first, for a SuperLink's).

``zk0 supernode``'s SuperNode starts this module as its SuperExec (``zk0.deployment.supernode``), and
so does zk0's simulation SuperLink (``zk0.deployment.superlink``) with ``--server``. It is Flower's
SuperExec, except that each ``flwr-clientapp`` process (a SuperNode's) or ``flwr-simulation`` and
``flwr-serverapp`` process (a SuperLink's) it launches is forked from a process that has already
imported Flower, and for a SuperLink PyTorch and lerobot (``zk0.deployment.forkserver``), instead
of started afresh; should that process be gone, Flower's own start takes over.
"""

from __future__ import annotations

import sys

from flwr.supercore.cli import flower_superexec
from flwr.supercore.constant import TaskType

from zk0 import internals
from zk0.deployment.forkserver import ForkServer


def main() -> None:
    server = sys.argv[1:2] == ["--server"]
    if server:
        del sys.argv[1]
    tasks = [TaskType.SERVER_APP, TaskType.SIMULATION] if server else [TaskType.CLIENT_APP]
    internals.start_tasks_with(tasks, ForkServer(server).start)
    sys.argv[0] = "flower-superexec"
    flower_superexec()


if __name__ == "__main__":
    main()
