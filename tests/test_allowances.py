"""The suite's time budget (tests/allowances.py): a test over its allowance fails the run in one
sentence naming it, and the long modules start first, one worker's share each."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.allowances import longest_first
from zk0.data.registry import PROJECT_ROOT


def test_a_test_over_its_allowance_fails_in_one_sentence_naming_it(tmp_path):
    (tmp_path / "conftest.py").write_text(
        "from tests.allowances import pytest_collection_modifyitems, pytest_runtest_makereport  # noqa: F401\n"
    )
    (tmp_path / "test_budget.py").write_text(
        "import time\nimport pytest\n\n"
        "@pytest.mark.allowance(0.2)\ndef test_slow():\n    time.sleep(0.8)\n\n"
        "@pytest.mark.allowance(5)\ndef test_within():\n    time.sleep(0.5)\n"
    )
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-W", "ignore::pytest.PytestUnknownMarkWarning",
         "--rootdir", str(tmp_path), str(tmp_path)],
        cwd=tmp_path, env={"PYTHONPATH": str(PROJECT_ROOT), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True,
        timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 1 and "1 failed, 1 passed" in done.stdout, done.stdout[-3000:] + done.stderr
    assert "test_budget.py::test_slow took 1 s, over its allowance of 0.2 s: make it faster" in done.stdout


class Item:
    """What ``longest_first`` reads of a pytest item: its file and its allowance marker."""

    def __init__(self, path: str, allowance: float | None = None):
        self.path, self.allowance = path, allowance

    def get_closest_marker(self, name: str):
        return pytest.mark.allowance(self.allowance).mark if self.allowance else None


def test_each_worker_s_share_starts_with_long_modules_kept_whole():
    items = [Item("a"), Item("a"), Item("b", 300), Item("b"), Item("c"), Item("d", 400), Item("e", 100), Item("f")]
    items += [Item("g") for _ in range(6)]
    ordered = longest_first(items, workers=2)
    assert sorted(map(id, ordered)) == sorted(map(id, items))
    first, second = ordered[: len(ordered) // 2], ordered[len(ordered) // 2 :]  # worksteal's two shares
    assert [i.path for i in first[:1]] == ["d"] and [i.path for i in second[:2]] == ["b", "b"]
    assert [i.path for i in second[2:3]] == ["e"], "the next longest goes to the share with less so far"
    assert longest_first(items, workers=1)[:4] == [items[5], items[2], items[3], items[6]]
