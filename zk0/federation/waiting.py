"""Waiting for owners: a round that finds fewer SuperNodes connected than it needs says so, and
gives up after ``wait-for-owners-s``.

Flower's ``sample_nodes`` asks the grid for the connected nodes once a second until there are at
least the strategy's minimum (zk0 sets it to ``min-train-clients``), logging a line each time and
never giving up. Owners go away: a robot switched off, a laptop closed, a SuperNode stopped. The
SuperLink drops a node at once on a clean stop, or after its heartbeats stop; whether the next
round waits depends on which comes first. ``OwnersWatch`` sees each of Flower's looks through a
wrapped grid (``watching``): the console hears once how many of how many are connected, again
only when that count changes, and after ``wait-for-owners-s`` (0: never) ``OwnersGone`` ends the
round loop. Flower's own once-a-second line stays in server.log.

A simulation's SuperNodes never come or go: one with fewer than ``min-train-clients`` is a
configuration that no wait mends, so it is refused in one sentence (``TooFewSimulatedOwners``)
once its SuperNodes have had ``SIMULATION_GRACE_S`` to register (Flower registers them while the
ServerApp starts), instead of after ``wait-for-owners-s``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

from flwr.serverapp import Grid

from zk0.artifacts.logs import say
from zk0.common.errors import Zk0Error
from zk0.config import ConfigError


class OwnersGone(Zk0Error):
    """A round waited ``wait-for-owners-s`` for enough owners, and they did not come."""


SIMULATION_GRACE_S = 10.0


class TooFewSimulatedOwners(ConfigError):
    """A simulation with fewer SuperNodes than ``min-train-clients``."""


class OwnersWatch:
    """How long the current round has waited for owners and what the console was last told."""

    def __init__(
        self, needed: int, limit_s: float, simulated: bool = False, clock: Callable[[], float] = time.monotonic
    ):
        self.needed = needed  # the strategy's minimum: min-train-clients
        self.limit_s = limit_s  # 0: wait as long as it takes
        self.simulated = simulated  # Flower's simulation: the SuperNodes it has are all it will have
        self.clock = clock
        self.since: float | None = None  # when this wait began; None while enough are connected
        self.said: int | None = None  # the connected count the console was last told

    def watching(self, grid: Grid, server_round: int) -> Grid:
        """``grid`` for Flower's sampling in ``server_round``: every look at the connected nodes
        passes through ``seen``."""
        return _WatchedGrid(grid, self, server_round)

    def seen(self, server_round: int, connected: int) -> None:
        """One look at the connected nodes: say what changed; past the limit, raise ``OwnersGone``."""
        if connected >= self.needed:
            if self.since is not None:
                say(
                    "Round {}: {} owners connected after {:.0f} s of waiting; the round goes on.",
                    server_round,
                    connected,
                    self.clock() - self.since,
                )
            self.since = self.said = None
            return
        now = self.clock()
        if self.since is None:
            self.since = now
        if self.simulated:
            if now - self.since >= SIMULATION_GRACE_S:
                raise TooFewSimulatedOwners(
                    f"This simulation has {connected} SuperNode(s) and min-train-clients={self.needed} needs "
                    f"{self.needed}; give it more (--federation-config \"num-supernodes={self.needed}\") or lower "
                    "min-train-clients."
                )
            return
        if connected != self.said:
            self.said = connected
            say("{}", self.waiting_sentence(server_round, connected))
        if self.limit_s and now - self.since >= self.limit_s:
            raise OwnersGone(
                f"Round {server_round} waited {self.limit_s:g} s (wait-for-owners-s) with {connected} of the "
                f"{self.needed} owners it needs connected"
            )

    def waiting_sentence(self, server_round: int, connected: int) -> str:
        """``Round 3 waits for owners: 1 of the 3 it needs (min-train-clients=3) are connected; ...``"""
        until = (
            f"the run ends if they are not back within wait-for-owners-s={self.limit_s:g} s"
            if self.limit_s
            else "it waits for them as long as it takes (wait-for-owners-s=0)"
        )
        return (
            f"Round {server_round} waits for owners: {connected} of the {self.needed} it needs "
            f"(min-train-clients={self.needed}) connected; {until}."
        )


class _WatchedGrid:
    """A Grid whose ``get_node_ids`` reports each count to an ``OwnersWatch``; the rest is the grid's."""

    def __init__(self, grid: Grid, watch: OwnersWatch, server_round: int):
        self._grid, self._watch, self._round = grid, watch, server_round

    def __getattr__(self, name: str):
        return getattr(self._grid, name)

    def get_node_ids(self) -> Iterable[int]:
        nodes = list(self._grid.get_node_ids())
        self._watch.seen(self._round, len(nodes))
        return nodes
