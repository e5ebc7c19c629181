"""The honest slow owner of the mixed-hardware tests and benchmarks (zk0.bench.throttle)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from zk0.bench.throttle import Throttle, working_in

BUSY = "while True: pass"


def test_a_throttled_folders_processes_get_their_share_of_the_cpu_and_run_again_after(tmp_path):
    """A busy process working in the folder gets about a quarter of the time it would (a core of
    its own: CPU seconds = wall seconds); one working elsewhere is left alone; after the ``with``
    it runs freely again."""
    owner, other = tmp_path / "robot-2", tmp_path / "robot-1"
    owner.mkdir()
    other.mkdir()
    slow = subprocess.Popen([sys.executable, "-c", BUSY], cwd=owner)
    free = subprocess.Popen([sys.executable, "-c", BUSY], cwd=other)
    try:
        assert working_in(owner) == [slow.pid]
        processes = psutil.Process(slow.pid), psutil.Process(free.pid)
        with Throttle(owner, share=0.25):
            time.sleep(0.3)
            before = [sum(p.cpu_times()[:2]) for p in processes]
            started = time.monotonic()
            time.sleep(2.0)
            wall = time.monotonic() - started
            used = [sum(p.cpu_times()[:2]) - b for p, b in zip(processes, before, strict=True)]
        assert used[0] < 0.45 * wall, f"the throttled process used {used[0]:.2f} s of {wall:.2f} s"
        assert used[0] < 0.6 * used[1], f"{used[0]:.2f} s against the free one's {used[1]:.2f} s"
        time.sleep(0.2)
        assert psutil.Process(slow.pid).status() != psutil.STATUS_STOPPED
    finally:
        slow.kill()
        free.kill()


def test_a_share_outside_0_to_1_is_refused():
    with pytest.raises(ValueError, match="must be in \\(0, 1\\], got 1.5"):
        Throttle(Path("."), share=1.5)
