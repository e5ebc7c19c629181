"""The app objects Flower loads from pyproject.toml import from the installed package."""

from __future__ import annotations

import importlib
import tomllib

from flwr.clientapp import ClientApp
from flwr.serverapp import ServerApp

from zk0.data.registry import PROJECT_ROOT


def test_components_named_in_pyproject_import():
    components = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["flwr"]["app"]["components"]
    loaded = {}
    for role, ref in components.items():
        module, attr = ref.split(":")
        loaded[role] = getattr(importlib.import_module(module), attr)
    assert isinstance(loaded["serverapp"], ServerApp)
    assert isinstance(loaded["clientapp"], ClientApp)
