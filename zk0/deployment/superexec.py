"""Flower's SuperExec, starting ClientApps from a fork server: ``python -m zk0.deployment.superexec`` takes
``flower-superexec``'s arguments.

``zk0 supernode``'s SuperNode starts this module as its SuperExec (``zk0.deployment.supernode``). It is
Flower's SuperExec, except that each ``flwr-clientapp`` process it launches is forked from a
process that has already imported Flower (``zk0.deployment.forkserver``) instead of started afresh; should
that process be gone, Flower's own start takes over.
"""

from __future__ import annotations

import sys

from flwr.supercore.cli import flower_superexec

from zk0 import internals
from zk0.deployment.forkserver import ForkServer


def main() -> None:
    internals.start_clientapps_with(ForkServer().start)
    sys.argv[0] = "flower-superexec"
    flower_superexec()


if __name__ == "__main__":
    main()
