"""Flower's SuperNode, waiting less: ``python -m zk0.supernode`` takes ``flower-supernode``'s arguments.

Flower's SuperNode (flwr 1.41 and 1.42) sleeps a hard-coded 3 s between polls of the SuperLink while it
has no message, and 0.5 s between looks for its ClientApp's reply; no flag or environment
variable sets either. A message sent to an idle SuperNode so waits 1.5 s on average before it
is even pulled, every round. ``zk0 supernode`` starts this module instead of
``flower-supernode``: the same SuperNode, with those two waits shortened
(``zk0.internals.shorten_supernode_waits``). It imports neither torch nor lerobot.
"""

from __future__ import annotations

import sys

from flwr.supernode.cli import flower_supernode

from zk0 import internals

IDLE_POLL_S = 0.5  # one small request to the SuperLink; twice a second per idle SuperNode
REPLY_POLL_S = 0.05  # a look at the SuperNode's own in-process state


def main() -> None:
    internals.shorten_supernode_waits(IDLE_POLL_S, REPLY_POLL_S)
    sys.argv[0] = "flower-supernode"
    flower_supernode()


if __name__ == "__main__":
    main()
