"""The suite's time budget: every test has an allowance in seconds, and the longest start first.

A test's allowance is ``@pytest.mark.allowance(seconds)`` or, unmarked, ``DEFAULT_S``; what it
spent is its set-up (fixtures it is the first to need, such as a module's federation) and its
body, as pytest's ``--durations`` reports them. A test over its allowance fails the run in one
sentence naming it. The figures and why each is what it is: tests/README.md.

pytest-xdist's ``worksteal`` gives each worker a contiguous share of the collected tests in order
and later moves tests from the end of a busy worker's share. So the order is built for that: the
modules holding allowed-long tests are dealt to the workers longest first (each module kept whole,
its fixtures set up once), each at the start of its worker's share, and the short tests fill the
rest of each share, where stealing takes them from.
"""

from __future__ import annotations

import os
from itertools import groupby

import pytest

DEFAULT_S = 180.0  # above the slowest unmarked test on a fresh 2-core machine (114 s): tests/README.md
SETUP = pytest.StashKey[float]()


def allowance(item: pytest.Item) -> float:
    marker = item.get_closest_marker("allowance")
    return float(marker.args[0]) if marker else DEFAULT_S


def longest_first(items: list[pytest.Item], workers: int) -> list[pytest.Item]:
    """``items`` reordered so that each of ``workers`` worksteal shares starts with its long modules."""
    modules = [list(group) for _, group in groupby(items, key=lambda item: item.path)]
    weight = {id(m): sum(allowance(i) for i in m if i.get_closest_marker("allowance")) for m in modules}
    long = sorted((m for m in modules if weight[id(m)]), key=lambda m: -weight[id(m)])
    short = [item for m in modules if not weight[id(m)] for item in m]
    shares: list[list[pytest.Item]] = [[] for _ in range(workers)]
    loads = [0.0] * workers
    for module in long:  # longest processing time first: each to the least-loaded share
        least = loads.index(min(loads))
        shares[least] += module
        loads[least] += weight[id(module)]
    ordered, left = [], len(items)
    for index, share in enumerate(shares):
        size = left // (workers - index)  # what worksteal hands this worker at the start
        fill = max(0, size - len(share))
        ordered += share + short[:fill]
        short = short[fill:]
        left -= len(share) + fill
    return ordered + short


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    items[:] = longest_first(items, workers)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    report = outcome.get_result()
    if call.when == "setup":
        item.stash[SETUP] = call.duration
    elif call.when == "call" and report.passed:
        spent, allowed = item.stash.get(SETUP, 0.0) + call.duration, allowance(item)
        if spent > allowed:
            report.outcome = "failed"
            report.longrepr = (
                f"{item.nodeid} took {spent:.0f} s, over its allowance of {allowed:g} s: make it faster, or raise "
                "its allowance in tests/README.md and its marker, saying why."
            )
