"""A simulation's Ray worker, forked from zk0's SuperLink instead of started afresh.

Ray starts a new Python process for each actor of a simulation run, and each pays Python's start,
Ray's, Flower's, PyTorch's and lerobot's imports (about 10 s of CPU of a minimal two-round run's
26) before its first step. zk0's SuperLink (``python -m zk0.deployment.superlink``) keeps a Ray
worker fork server that imported those once (``zk0.deployment.forkserver``), and each run's
``flwr-simulation`` tells Ray (``internals.start_ray_workers_with``) to start its workers with
this module in place of ``python``: Ray runs ``python -m zk0.deployment.rayworker default_worker.py
<Ray's arguments>``, and this process, which imports only the standard library, hands the
arguments, its environment, its folder and its output files to the fork server, which forks the
worker. This process stays as the one Ray started, and exits with the worker's code; if Ray kills
it, the fork server kills the worker. Without the fork server (``ZK0_RAY_WORKERS`` unset or its
socket gone) the worker starts as Ray would start it.
"""

from __future__ import annotations

import json
import os
import socket
import sys

SOCKET_ENV = "ZK0_RAY_WORKERS"  # the fork server's socket, in the environment Ray gives its workers
MAX_REQUEST = 1 << 20  # a worker's arguments and environment, in one message


def request(args: list[str]) -> bytes:
    """What the fork server needs to start the worker as Ray would have: its command line, environment and folder."""
    return json.dumps({"args": args, "env": dict(os.environ), "cwd": os.getcwd()}).encode()


def main(args: list[str]) -> int:
    """Have the fork server run Ray's worker ``args`` with this process's standard streams; return its exit code."""
    path = os.environ.get(SOCKET_ENV, "")
    try:
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        conn.connect(path)
        socket.send_fds(conn, [request(args)], [0, 1, 2])
    except OSError:  # no fork server: start the worker as Ray would have
        os.execv(sys.executable, [sys.executable, *args])
    code = conn.recv(16)  # the worker's exit code, once it has exited
    return int(code) if code else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
