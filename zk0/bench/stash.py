"""What a long benchmark has finished, kept in its output folder so the same command continues.

The sim-cube study trains a dozen models per training seed and rolls each out on hundreds of
episodes: two and a half hours on a 2-core machine. A ``Stash`` keeps each trained model's weights
and each finished figure (a rollout's outcomes, an offline evaluation) under its folder as soon as
it exists, written to a temporary name and renamed, so a stopped run leaves only complete files;
run again, the benchmark takes them instead of training or rolling out again, and a federation
stopped part-way continues from its last round (zk0.bench.models.continuation). Whatever the
stash does not have is computed exactly as an uninterrupted run computes it, so the figures are
the same either way (the study resets every data order before each model: zk0.bench.study).

The folder remembers the settings its models were trained with; a command with other settings is
refused in one sentence instead of mixing models trained two ways.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from zk0.common.errors import Zk0Error

SETTINGS_FILE = "settings.json"


def _slug(name: str) -> str:
    """A model or figure name as a file name (``local 0`` -> ``local-0``)."""
    return name.replace(" ", "-").replace("/", "-")


def _replace(path: Path, write: Callable[[Path], None]) -> None:
    """Write through a temporary file beside ``path`` and rename it: never half a file at ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    write(partial)
    os.replace(partial, path)


class Stash:
    """Finished models and figures under ``folder``, trained with ``settings``."""

    def __init__(self, folder: Path, settings: dict[str, Any]) -> None:
        self.folder = folder
        recorded = folder / SETTINGS_FILE
        if recorded.is_file():
            before = json.loads(recorded.read_text())
            changed = sorted(k for k in {*before, *settings} if before.get(k) != settings.get(k))
            if changed:
                key = changed[0]
                raise Zk0Error(
                    f"{str(folder)!r} holds models trained with {key} = {before.get(key)!r}, not "
                    f"{settings.get(key)!r}: give another --output-dir, or remove that folder to start over."
                )
        else:
            _replace(recorded, lambda p: p.write_text(json.dumps(settings, indent=2, sort_keys=True)))

    def weights(self, label: str, train: Callable[[], dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        """Model ``label``'s weights: kept from an earlier run, or trained now and kept."""
        path = self.folder / "models" / f"{_slug(label)}.safetensors"
        if path.is_file():
            return load_file(path)
        weights = train()
        _replace(path, lambda p: save_file({k: v.contiguous() for k, v in weights.items()}, p))
        return weights

    def _figures_path(self, name: str) -> Path:
        *folders, file = (_slug(part) for part in name.split("/"))
        return self.folder.joinpath(*folders, f"{file}.json")

    def figures(self, name: str, compute: Callable[[], Any]) -> Any:
        """Figures ``name`` (JSON; ``/`` makes folders): kept from an earlier run, or computed now and kept."""
        path = self._figures_path(name)
        if path.is_file():
            return json.loads(path.read_text())
        value = compute()
        _replace(path, lambda p: p.write_text(json.dumps(value, indent=2)))
        return value

    def has(self, name: str) -> bool:
        """Whether figures ``name`` are kept."""
        return self._figures_path(name).is_file()
