"""The import contracts in pyproject's ``[tool.importlinter]`` (packages layered from the entry points
down to common and internals, the simulator apart from the federation, no circles) hold, and they
catch the kinds of import that broke them before."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from zk0.data.registry import PROJECT_ROOT


def lint_imports(root: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` on the zk0 package and pyproject.toml found in ``root``."""
    return subprocess.run(
        [str(Path(sys.executable).parent / "lint-imports"), "--no-cache"], cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)}, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip


def test_the_import_contracts_hold():
    done = lint_imports(PROJECT_ROOT)
    assert done.returncode == 0 and "Contracts: 3 kept, 0 broken." in done.stdout, done.stdout[-3000:]


def test_a_circle_or_an_import_up_a_layer_breaks_them(tmp_path):
    """The two circles of 2026-12-02, put back in a copy of the package: the simulator asking the asset
    generator for the cache root, and the LoRA benchmark building on the learning benchmark."""
    shutil.copytree(PROJECT_ROOT / "zk0", tmp_path / "zk0", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(PROJECT_ROOT / "pyproject.toml", tmp_path)
    for module, line in (
        ("sim/scene.py", "from zk0.data.assets import ensure_dataset"),
        ("bench/lora.py", "from zk0.bench.learning import actions"),
    ):
        path = tmp_path / "zk0" / module
        path.write_text(f"{path.read_text()}\n{line}  # noqa\n")
    done = lint_imports(tmp_path)
    assert done.returncode == 1 and "Contracts: 1 kept, 2 broken." in done.stdout, done.stdout[-3000:]
    assert "zk0.sim is not allowed to import zk0.data:\n\n- zk0.sim.scene -> zk0.data.assets" in done.stdout
    assert "No cycles are allowed in zk0.\n" in done.stdout and "- .sim -> .data (1 import)" in done.stdout
    assert "No cycles are allowed in zk0.bench." in done.stdout and "- .lora -> .learning (1 import)" in done.stdout
