"""zk0: federated fine-tuning of SmolVLA across SO-100/SO-101 robot arms (a Flower app)."""

from __future__ import annotations

import functools
import hashlib
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent


@functools.cache
def app_fingerprint() -> str:
    """``<version>+<hash of every .py file of this package>``: which zk0 code this process runs.

    Flower loads the app from the bundle ``flwr run`` submitted (its folder comes first on
    ``sys.path``), so the server and every client should report the same value; the server
    sends its own and a client with other code refuses it, naming both. A simulation's Ray workers
    can import the installed zk0 instead (seen with an editable install: an edit to zk0's source
    while a run was going made every client refuse the server's code in the next round).
    """
    digest = hashlib.sha256()
    for path in sorted(PACKAGE.rglob("*.py")):
        digest.update(path.relative_to(PACKAGE).as_posix().encode())
        digest.update(path.read_bytes())
    pyproject = PACKAGE.parent / "pyproject.toml"
    found = re.search(r'^version = "([^"]+)"', pyproject.read_text(), re.MULTILINE) if pyproject.is_file() else None
    return f"{found.group(1) if found else 'unknown'}+{digest.hexdigest()[:12]}"
