"""Offline assets: the synthetic datasets and the tiny backbone, generated once and cached.

Nothing here touches the Hugging Face Hub. Each asset lives in its own folder under
the cache root with a ``zk0_manifest.json`` naming the generator version and seed;
a folder whose manifest is missing or differs is regenerated. Generation writes to a
temporary sibling and renames it into place under a file lock, so parallel test
workers and interrupted runs never see half an asset.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from filelock import FileLock
from loguru import logger

from zk0.common.cache import default_cache_root
from zk0.common.errors import Zk0Error
from zk0.config import OFFLINE_MODELS
from zk0.data.assets.datasets import SPECS
from zk0.sim.tasks import RECORDER_VERSION, SIM_SPECS

GENERATOR_VERSION = 1
MANIFEST = "zk0_manifest.json"
TINY_BACKBONE = "tiny-smolvlm"
TINY_128_BACKBONE = "tiny-smolvlm-128"
FULL_SIZE_BACKBONE = "smolvlm2-500m-random"
BACKBONES = (TINY_BACKBONE, TINY_128_BACKBONE, FULL_SIZE_BACKBONE)
# The generated backbone (random weights) each offline run-config `model` value is built on.
OFFLINE_BACKBONES = dict(zip(OFFLINE_MODELS, BACKBONES, strict=True))


class AssetError(Zk0Error):
    """A bad asset request; the message is one sentence naming the bad value."""


def _writable_root(root: Path) -> Path:
    try:
        root.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=root):
            pass
    except OSError as err:
        raise AssetError(
            f"Cache dir {str(root)!r} is not writable ({err.strerror}); pick another with --cache-dir or ZK0_CACHE."
        ) from None
    return root


def _ensure(target: Path, manifest: dict, build: Callable[[Path], None]) -> Path:
    """Return ``target``, (re)building it with ``build(tmp_dir)`` unless its manifest matches."""
    if _manifest_matches(target, manifest):
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(target) + ".lock"):
        if _manifest_matches(target, manifest):
            return target
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
        try:
            build(staging / "asset")
            (staging / "asset" / MANIFEST).write_text(json.dumps(manifest, sort_keys=True))
            if target.exists():
                shutil.rmtree(target)
            (staging / "asset").rename(target)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return target


def _recorded(target: Path) -> dict | None:
    """The manifest of the asset at ``target`` (None: none there, or unreadable)."""
    try:
        return json.loads((target / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def _manifest_matches(target: Path, manifest: dict) -> bool:
    return _recorded(target) == manifest


def ensure_backbone(root: Path | None = None, kind: str = TINY_BACKBONE) -> Path:
    """A generated SmolVLM backbone dir (tiny, tiny with 128 px cameras, or SmolVLM2-500M-shaped), built if
    missing or stale."""
    if kind not in BACKBONES:
        raise AssetError(f"Unknown backbone {kind!r}; expected one of {list(BACKBONES)}.")
    root = _writable_root(root or default_cache_root())
    manifest = {"asset": kind, "version": GENERATOR_VERSION}
    return _ensure(root / "backbones" / kind, manifest, lambda out: _build_backbone(out, kind))


def _build_backbone(out: Path, kind: str) -> None:
    # transformers and lerobot load only to build an asset: checking that one is there stays fast.
    from zk0.data.assets.backbone import SMOLVLM2_500M, TINY, TINY_128, build_backbone

    shapes = {TINY_BACKBONE: TINY, TINY_128_BACKBONE: TINY_128, FULL_SIZE_BACKBONE: SMOLVLM2_500M}
    build_backbone(out, shapes[kind])


def generated_spec(name: str):
    """The spec of a dataset zk0 generates: synthetic frames (``SPECS``) or simulator
    demonstrations (``zk0.sim.tasks.SIM_SPECS``)."""
    spec = SPECS.get(name) or SIM_SPECS.get(name)
    if spec is None:
        raise AssetError(f"Unknown generated dataset {name!r}; expected one of {[*SPECS.described(), *SIM_SPECS.described()]}.")
    return spec


def _write_dataset(out: Path, name: str, seed: int, episodes: int | None) -> None:
    if name in SIM_SPECS:  # MuJoCo loads only to record demonstrations
        from zk0.sim.record import record_demonstrations

        record_demonstrations(SIM_SPECS[name], out, seed, episodes)
        return
    from zk0.data.assets.datasets import write_synthetic_dataset

    write_synthetic_dataset(SPECS[name], out, seed, episodes)


def synthetic_dataset_root(name: str, root: Path | None = None) -> Path:
    """Where the generated dataset ``name`` lives (a LeRobotDataset root)."""
    return (root or default_cache_root()) / "datasets" / generated_spec(name).repo_id


def generated_dataset(name: str, root: Path | None = None) -> Path | None:
    """The synthetic dataset ``name`` if this machine has generated it (any seed), else None.

    Opening a dataset only looks; generating is an explicit step (``zk0 assets``, which
    ``./train.sh`` runs, the benchmarks' and the tests' set-up).
    """
    target = synthetic_dataset_root(name, root)
    try:
        manifest = json.loads((target / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    current = manifest.get("recorder") == RECORDER_VERSION if name in SIM_SPECS else True
    return target if manifest.get("asset") == name and manifest.get("version") == GENERATOR_VERSION and current else None


def ensure_dataset(name: str, root: Path | None = None, seed: int = 0, episodes: int | None = None) -> Path:
    """The synthetic dataset ``name`` as a LeRobotDataset root, generated if missing or stale.

    With ``episodes`` None, a dataset generated the same way with at least its default number of
    episodes is taken as it is: ``zk0 assets --episodes 30`` records 30 and the run after it (train.sh's
    asset step asks for no count) trains on those 30. A count asked for and different from what is
    there records it again, and says so in one sentence."""
    target = synthetic_dataset_root(name, root)
    if episodes is not None and episodes < 1:
        raise AssetError(f"Episode count {episodes} for {name!r} is invalid; expected a positive integer.")
    _writable_root(root or default_cache_root())
    spec = generated_spec(name)
    manifest = {"asset": name, "version": GENERATOR_VERSION, "seed": seed, "episodes": episodes or spec.episodes}
    if name in SIM_SPECS:
        manifest["recorder"] = RECORDER_VERSION
    recorded = _recorded(target)
    if recorded and recorded == {**manifest, "episodes": recorded.get("episodes")}:
        if episodes is None and recorded["episodes"] >= manifest["episodes"]:
            return target  # what its owner recorded with --episodes stays: a run asking for no count takes it
        if recorded["episodes"] != manifest["episodes"]:
            logger.warning(
                "Recording {!r} again with {} episodes in place of the {} it has: {}.",
                name, manifest["episodes"], recorded["episodes"],
                f"{episodes} were asked for" if episodes else f"it has fewer than its default {spec.episodes}",
            )  # fmt: skip
    _quiet_video_encoders()
    return _ensure(target, manifest, lambda tmp: _write_dataset(tmp, name, seed, episodes))


def ensure_all(root: Path | None = None, seed: int = 0) -> dict[str, Path]:
    """Every offline asset the federation uses: the tiny backbone and the synthetic datasets."""
    paths = {TINY_BACKBONE: ensure_backbone(root)}
    paths.update({name: ensure_dataset(name, root, seed) for name, spec in SPECS.items() if not spec.benchmark_only})
    return paths


def _quiet_video_encoders() -> None:
    """SVT-AV1 prints a banner per video to stderr; keep only its errors."""
    os.environ.setdefault("SVT_LOG", "1")
