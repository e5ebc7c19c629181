"""A round short of owners: what the console hears while Flower's sampling waits, and when it gives up.
(On the Deployment Engine: tests/test_deployment.py, where owners really leave and come back.)"""

from __future__ import annotations

import pytest
from loguru import logger

from zk0.federation.waiting import SIMULATION_GRACE_S, OwnersGone, OwnersWatch, TooFewSimulatedOwners


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def console():
    said = []
    sink = logger.add(lambda m: said.append(m.record["message"]), filter=lambda r: r["extra"].get("console"))
    yield said
    logger.remove(sink)


def test_the_console_hears_of_a_wait_once_and_again_only_when_the_count_changes(console):
    clock = Clock()
    watch = OwnersWatch(needed=3, limit_s=300, clock=clock)
    watch.seen(2, 3)  # enough: Flower samples at once, nothing said
    assert console == []
    for connected in (1, 1, 1, 2, 2):  # Flower looks once a second
        clock.now += 1
        watch.seen(3, connected)
    assert console == [
        "Round 3 waits for owners: 1 of the 3 it needs (min-train-clients=3) connected; the run ends if they are not "
        "back within wait-for-owners-s=300 s.",
        "Round 3 waits for owners: 2 of the 3 it needs (min-train-clients=3) connected; the run ends if they are not "
        "back within wait-for-owners-s=300 s.",
    ]
    clock.now += 1
    watch.seen(3, 3)
    assert console[-1] == "Round 3: 3 owners connected after 5 s of waiting; the round goes on."
    clock.now += 1000  # a later wait starts its own clock and is said again
    watch.seen(4, 2)
    assert len(console) == 4 and console[-1].startswith("Round 4 waits for owners: 2 of the 3")


def test_a_wait_ends_after_wait_for_owners_s_and_counts_from_its_first_look(console):
    clock = Clock()
    watch = OwnersWatch(needed=2, limit_s=30, clock=clock)
    watch.seen(5, 1)
    clock.now += 29
    watch.seen(5, 0)  # the count changed: said, the wait goes on from its start
    clock.now += 1
    with pytest.raises(OwnersGone, match=r"^Round 5 waited 30 s \(wait-for-owners-s\) with 0 of the 2 owners"):
        watch.seen(5, 0)
    assert len(console) == 2


def test_wait_for_owners_s_0_waits_as_long_as_it_takes(console):
    clock = Clock()
    watch = OwnersWatch(needed=2, limit_s=0, clock=clock)
    for _ in range(5):
        clock.now += 3600
        watch.seen(1, 1)
    assert console == [
        "Round 1 waits for owners: 1 of the 2 it needs (min-train-clients=2) connected; it waits for them as long as "
        "it takes (wait-for-owners-s=0)."
    ]


def test_a_simulation_short_of_owners_is_refused_once_its_supernodes_have_registered(console):
    """Flower's simulation has every SuperNode it will ever have: after the grace its registration
    takes, one sentence that says what to change; nothing waits wait-for-owners-s for nodes that
    cannot come, and the console hears no waiting sentence."""
    clock = Clock()
    watch = OwnersWatch(needed=3, limit_s=300, simulated=True, clock=clock)
    watch.seen(1, 0)  # a look before Flower registered the nodes
    clock.now += SIMULATION_GRACE_S - 1
    watch.seen(1, 2)
    clock.now += 1
    with pytest.raises(TooFewSimulatedOwners) as refused:
        watch.seen(1, 2)
    assert str(refused.value) == (
        'This simulation has 2 SuperNode(s) and min-train-clients=3 needs 3; give it more (--federation-config '
        '"num-supernodes=3") or lower min-train-clients.'
    )
    assert console == []
    enough = OwnersWatch(needed=2, limit_s=300, simulated=True, clock=clock)
    enough.seen(1, 0)
    clock.now += 2
    enough.seen(1, 2)  # registered within the grace: the round goes on
