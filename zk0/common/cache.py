"""Where zk0 keeps what it generates and caches on this machine.

The offline assets, the simulator's decimated meshes, each dataset's decoded frames, compiled
kernels and the benchmarks' starting points all live under one root. Every layer needs to know
where that is, and none should import the asset generator to find out.
"""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_root() -> Path:
    """``$ZK0_CACHE``, else ``$XDG_CACHE_HOME/zk0``, else ``~/.cache/zk0``."""
    if os.environ.get("ZK0_CACHE"):
        return Path(os.environ["ZK0_CACHE"]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "zk0"
