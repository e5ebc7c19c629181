"""Pre-flight check of a dataset: everything its metadata can show wrong, before anything trains.

Community recordings come in older layouts, without cameras, for other arms, with video files
missing or empty. ``check_dataset`` opens a registry entry's metadata (never a frame) and
refuses such a dataset in one sentence naming it, the value and what was expected. It is the
one check everywhere: ``zk0 check``, the ServerApp before round 1 of a simulation, ``zk0
supernode`` before it connects, and a client when it opens its dataset. A dataset with a local
``root`` is checked without touching the network: lerobot would otherwise try the Hub for any
metadata or video file it cannot find there.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from huggingface_hub import constants as hub_constants
from lerobot.configs import FeatureType
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata

from zk0.common.errors import Zk0Error
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.data.loaders import DataError, open_metadata
from zk0.data.registry import DatasetEntry, Registry
from zk0.learning.policy import PolicyError, config_features, policy_config, resolve_device

LAYOUT = "v3"  # lerobot 0.6 reads LeRobotDataset v3.x
SIZED = ("observation.state", "action")


@dataclass(frozen=True)
class ModelInputs:
    """What a dataset must feed: the global model's camera inputs and its state/action sizes."""

    cameras: tuple[str, ...]
    shapes: dict[str, tuple[int, ...]] = field(default_factory=dict)  # empty: not known on this machine


def model_inputs(run: RunConfig, registry_cameras: list[str], shapes: dict | None = None) -> ModelInputs:
    """A pretrained policy's own inputs, or for a fresh policy the registry's cameras and ``shapes``
    (those of the global model, which the server builds from its evaluation dataset)."""
    if run.model in OFFLINE_MODELS:
        return ModelInputs(tuple(registry_cameras), {k: tuple(v) for k, v in (shapes or {}).items()})
    try:
        cfg = policy_config(run, resolve_device("cpu"))
    except PolicyError:
        raise
    except Exception as err:  # Hub, file and JSON errors all mean the same thing here
        raise PolicyError(f"Model {run.model!r} cannot be opened ({type(err).__name__}: {err}).") from None
    features = config_features(cfg)
    cameras = tuple(sorted(k for k, ft in features.items() if ft.type is FeatureType.VISUAL))
    return ModelInputs(cameras, {k: tuple(features[k].shape) for k in SIZED if k in features})


def dataset_shapes(meta: LeRobotDatasetMetadata) -> dict[str, tuple[int, ...]]:
    """The state and action sizes a dataset records (a fresh global model takes its server dataset's)."""
    return {key: tuple(meta.features[key]["shape"]) for key in SIZED if key in meta.features}


def check_dataset(entry: DatasetEntry, inputs: ModelInputs, eval_episodes: int | None) -> LeRobotDatasetMetadata:
    """The entry's metadata, or a ``DataError`` naming the first thing that would stop training.

    ``eval_episodes`` is the run's held-out count for a client dataset (None: a dataset that is
    only evaluated, or a run not known yet, as on a SuperNode before it connects).
    """
    root = entry.local_root()
    if root is not None:
        _check_local_layout(entry, root)
    meta = open_metadata(entry)
    _check_features(entry, meta, inputs)
    needed = 1 if eval_episodes is None else eval_episodes + 1
    if meta.total_episodes < needed:
        held_out = f"eval-episodes={eval_episodes} held out and one to train on" if eval_episodes else "one"
        raise DataError(
            f"Dataset {entry.name!r} has {meta.total_episodes} episodes; expected at least {needed} ({held_out})."
        )
    if root is not None:
        _check_files(entry, meta, root)
    return meta


def _check_local_layout(entry: DatasetEntry, root: Path) -> None:
    """A local root holds a v3 LeRobotDataset's metadata (what lerobot would fetch from the Hub if not)."""
    info_file = root / "meta" / "info.json"
    if not info_file.is_file():
        raise DataError(
            f"Dataset {entry.name!r} has no {str(info_file)!r}; expected a LeRobotDataset at its root {str(root)!r}."
        )
    try:
        version = str(json.loads(info_file.read_text()).get("codebase_version", "unknown"))
    except (OSError, ValueError) as err:
        raise DataError(f"Dataset {entry.name!r} has an unreadable {str(info_file)!r} ({err}).") from None
    if not version.startswith(LAYOUT):
        open_metadata(entry)  # lerobot's own refusal, with the conversion command
        raise DataError(f"Dataset {entry.name!r} is in LeRobot layout {version}; expected {LAYOUT}.x.")
    for needed in ("meta/tasks.parquet", "meta/episodes"):
        if not (root / needed).exists():
            raise DataError(
                f"Dataset {entry.name!r} has no {needed!r} under {str(root)!r}; its metadata is incomplete."
            )


def _check_features(entry: DatasetEntry, meta: LeRobotDatasetMetadata, inputs: ModelInputs) -> None:
    for key in SIZED:
        if key not in meta.features:
            raise DataError(f"Dataset {entry.name!r} has no {key!r} feature; the policy needs joint state and actions.")
        shape, expected = tuple(meta.features[key]["shape"]), inputs.shapes.get(key)
        if expected is not None and shape != expected:
            raise DataError(
                f"Dataset {entry.name!r} has {key!r} of size {list(shape)}; the model expects {list(expected)} "
                "(every dataset of a federation must record the same arm)."
            )
    recorded = sorted(key.removeprefix("observation.images.") for key in meta.camera_keys)
    if not recorded:
        raise DataError(f"Dataset {entry.name!r} records no camera; the policy needs at least one camera image.")
    for camera in entry.cameras:
        if camera not in recorded:
            raise DataError(
                f"Dataset {entry.name!r} has no camera {camera!r}, which its registry entry maps; "
                f"expected one of its cameras {recorded}."
            )
    rename = entry.rename_map()
    mapped = {rename.get(key, key) for key in meta.camera_keys} & set(inputs.cameras)
    if not mapped:
        raise DataError(
            f"Dataset {entry.name!r} has no camera mapped onto the model's inputs {list(inputs.cameras)}; "
            f"map one of its cameras {recorded} in its registry entry (cameras = {{...}})."
        )


def check_episodes(entry: DatasetEntry, meta: LeRobotDatasetMetadata, episodes: list[int]) -> None:
    """``episodes`` of a local dataset (recorded since a run opened it) as the pre-flight checks a
    dataset: every file they point to there and not empty (a ``DataError`` naming the first that is not)."""
    root = entry.local_root()
    if root is not None:
        _check_files(entry, meta, root, episodes)


def _check_files(
    entry: DatasetEntry, meta: LeRobotDatasetMetadata, root: Path, episodes: list[int] | None = None
) -> None:
    """Every data and video file an episode (of ``episodes``; default all) points to is there and not empty."""
    files = set()
    for episode in range(meta.total_episodes) if episodes is None else episodes:
        files.add(meta.get_data_file_path(episode))
        files.update(meta.get_video_file_path(episode, key) for key in meta.video_keys)
    for relative in sorted(files):
        path = root / relative
        if not path.is_file():
            raise DataError(
                f"Dataset {entry.name!r} lacks {str(relative)!r}, which its episodes use, under {str(root)!r}."
            )
        if path.stat().st_size == 0:
            raise DataError(f"Dataset {entry.name!r} has an empty (0-byte) {str(relative)!r} under {str(root)!r}.")


def on_this_machine(entry: DatasetEntry) -> bool:
    """Whether ``entry`` can be checked here: generated, a local root that exists, or (offline) a
    Hub dataset whose metadata is cached. Others (another owner's disk, the Hub) are skipped."""
    if entry.synthetic:
        return True
    if entry.root:
        return Path(entry.root).expanduser().is_dir()
    if not hub_constants.HF_HUB_OFFLINE:
        return True
    try:
        open_metadata(entry)
    except DataError:  # not cached: nothing to check offline
        return False
    return True


@dataclass
class Report:
    """What ``check_federation`` found: one sentence per refused dataset, the names of those checked
    and skipped, and the server dataset's metadata when it passed."""

    problems: list[str] = field(default_factory=list)
    checked: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    server_meta: LeRobotDatasetMetadata | None = None


def check_federation(run: RunConfig, registry: Registry, clients: bool = True, skip_absent: bool = True) -> Report:
    """Check the server's evaluation dataset, then (``clients``) every client dataset, against the model.

    A fresh global model is built from the server's evaluation dataset, so its sizes are the
    ones client datasets must match. ``skip_absent`` skips entries that are not on this machine
    (another owner's disk, an uncached Hub dataset offline) instead of failing on them.
    """
    report = Report()
    server = registry.get(run.server_eval_dataset)
    inputs = None  # a pretrained model's config is opened only when a dataset here needs it
    for entry in [server, *registry.clients] if clients else [server]:
        if skip_absent and not on_this_machine(entry):
            report.skipped.append(entry.name)
            continue
        inputs = inputs or model_inputs(run, registry.model_cameras())
        try:
            meta = check_dataset(entry, inputs, None if entry is server else run.eval_episodes)
        except Zk0Error as err:  # the dataset's problems, or a generated one not generated yet
            report.problems.append(str(err))
            continue
        report.checked.append(entry.name)
        if entry is server:
            report.server_meta = meta
            if not inputs.shapes:
                inputs = ModelInputs(inputs.cameras, dataset_shapes(meta))
    return report
