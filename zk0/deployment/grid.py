"""Flower's Grid, waiting for replies 0.2 s at a time instead of 3 s.

Flower's ServerApp grid (1.41, 1.42) pushes a round's messages, then pulls replies and sleeps a fixed
3 s between pulls, so every phase of every round ends on the next multiple of 3 s: on a
SuperNode federation that is 1.5 s per phase on average, more than the whole round's work on
short rounds. ``PromptGrid`` does the same with Flower's own public ``push_messages`` and
``pull_messages`` and a short pause (a pull is one local call to the SuperLink).

It also keeps a round's deadline (``round-deadline-s``): a train phase after this process's
first (which builds every client, so it is exempt) waits at most that long, and the server
aggregates what arrived; a late reply is dropped (the strategy names its client).
"""

from __future__ import annotations

import time
from collections.abc import Iterable

from flwr.app import Message, MessageType
from flwr.serverapp import Grid

POLL_S = 0.2


class PromptGrid:
    """Every Grid method is the wrapped grid's, except ``send_and_receive``."""

    def __init__(self, grid: Grid, poll_s: float = POLL_S, train_deadline_s: float = 0.0):
        self._grid = grid
        self.poll_s = poll_s
        self.train_deadline_s = train_deadline_s  # 0: a train phase waits as long as the phase timeout
        self.train_phases = 0

    def __getattr__(self, name: str):
        return getattr(self._grid, name)

    def send_and_receive(self, messages: Iterable[Message], *, timeout: float | None = None) -> Iterable[Message]:
        """Push ``messages`` and return the replies that arrive within ``timeout`` seconds (None: all),
        or within the round's deadline for a train phase after the first."""
        messages = list(messages)
        if messages and all(m.metadata.message_type == MessageType.TRAIN for m in messages):
            if self.train_deadline_s and self.train_phases:
                timeout = self.train_deadline_s if timeout is None else min(timeout, self.train_deadline_s)
            self.train_phases += 1
        waiting = set(self._grid.push_messages(messages))
        deadline = None if timeout is None else time.monotonic() + timeout
        replies: list[Message] = []
        while waiting:
            arrived = list(self._grid.pull_messages(waiting))
            replies += arrived
            waiting -= {msg.metadata.reply_to_message_id for msg in arrived}
            now = time.monotonic()
            if not waiting or (deadline is not None and now >= deadline):
                break
            time.sleep(self.poll_s if deadline is None else min(self.poll_s, deadline - now))  # a last pull at it
        return replies
