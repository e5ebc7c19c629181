"""Flower's SuperLink, starting each run warm: ``python -m zk0.deployment.superlink`` takes
``flower-superlink``'s arguments.

With ``--isolation subprocess`` Flower's SuperLink starts a SuperExec, which starts a new
``flwr-simulation`` (or ``flwr-serverapp``) process for every run: Python, Flower, PyTorch and
lerobot imported again, about 10 s of CPU before the ServerApp's first line on 2 cores. zk0's
simulation SuperLink (``zk0.deployment.simulation``: the benchmarks' and the tests' federations)
runs this module instead of ``flower-superlink``: the same SuperLink, whose SuperExec forks each
run's process from one that has imported those already (``zk0.deployment.superexec --server``).
"""

from __future__ import annotations

import sys

from flwr.superlink.cli import flower_superlink

from zk0 import internals


def main() -> None:
    internals.start_superlinks_superexec_as([sys.executable, "-m", "zk0.deployment.superexec", "--server"])
    sys.argv[0] = "flower-superlink"
    flower_superlink()


if __name__ == "__main__":
    main()
