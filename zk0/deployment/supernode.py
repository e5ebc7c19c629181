"""Flower's SuperNode, waiting less: ``python -m zk0.deployment.supernode`` takes ``flower-supernode``'s arguments.

Flower's SuperNode (flwr 1.41 and 1.42) sleeps a hard-coded 3 s between polls of the SuperLink
while it has no message and 0.5 s between looks for its ClientApp's reply, and retries an array
not uploaded yet after 1 s; no flag or environment variable sets any of them. A message sent to
an idle SuperNode so waited 1.5 s on average before it was even pulled, and a second more for its
arrays, every round. It also beats every 30 s, and the SuperLink gives a node up after two beats
missed: a robot switched off held its round a minute before the server heard it was gone.
``zk0 supernode`` starts this module instead of ``flower-supernode``: the
same SuperNode with those waits shortened (``zk0.internals``), whose SuperExec forks each
message's ClientApp process from one that has imported Flower already (``zk0.deployment.superexec``). It
imports neither torch nor lerobot.
"""

from __future__ import annotations

import sys

from flwr.supernode.cli import flower_supernode

from zk0 import internals

IDLE_POLL_S = 0.5  # one small request to the SuperLink; twice a second per idle SuperNode
REPLY_POLL_S = 0.05  # a look at the SuperNode's own in-process state
HEARTBEAT_S = 10  # the shortest the SuperLink accepts: a node gone is answered for within 20 s


def main() -> None:
    internals.shorten_supernode_waits(IDLE_POLL_S, REPLY_POLL_S)
    internals.set_supernode_heartbeat(HEARTBEAT_S)
    internals.shorten_object_pull_backoff()  # the arrays it pulls from the SuperLink
    internals.start_superexec_as([sys.executable, "-m", "zk0.deployment.superexec"])
    sys.argv[0] = "flower-supernode"
    flower_supernode()


if __name__ == "__main__":
    main()
