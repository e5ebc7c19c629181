"""Open a registry entry as LeRobotDatasets through lerobot's ``make_dataset``.

Frames come from the decoded-frame cache (``zk0.data.frames``) when it fits ``frame-cache-gb``.
The last ``eval-episodes`` episodes are held out for evaluation and never trained on.
Batches come from a plain ``DataLoader`` over lerobot's ``EpisodeAwareSampler``, as in
lerobot's own training script; ``prepare_batch`` does what that script does between
the loader and the preprocessor (uint8 frames to [0, 1]), on the device rather than the
host, plus the registry's task text.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets import EpisodeAwareSampler
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.factory import make_dataset
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.utils import BackwardCompatibilityError
from loguru import logger
from torch.utils.data import DataLoader

from zk0.common import machine
from zk0.common.cache import default_cache_root
from zk0.common.errors import Zk0Error
from zk0.config import RunConfig
from zk0.data.frames import attach_frame_cache
from zk0.data.registry import DatasetEntry


class DataError(Zk0Error):
    """A dataset that cannot be split or opened as asked; one sentence naming it."""


@dataclass
class DatasetSplit:
    """The training and held-out episodes of one dataset, opened for one policy config."""

    entry: DatasetEntry
    meta: LeRobotDatasetMetadata
    train: LeRobotDataset | None
    evaluation: LeRobotDataset


def open_metadata(entry: DatasetEntry) -> LeRobotDatasetMetadata:
    """The dataset's metadata (features, stats, episodes) without opening any video."""
    try:
        return LeRobotDatasetMetadata(entry.repo_id, root=entry.local_root(), revision=entry.revision)
    except BackwardCompatibilityError:
        raise DataError(
            f"Dataset {entry.name!r} ({entry.repo_id}) is in an older LeRobot format; convert it to v3.0 with "
            f"`python -m lerobot.scripts.convert_dataset_v21_to_v30 --repo-id={entry.repo_id}` and pin the new revision."
        ) from None
    except OSError as err:  # Hub and file errors (offline, no such repo or revision, unreadable files)
        where = f"at {entry.root!r}" if entry.root else "on the Hugging Face Hub or in its cache (HF_LEROBOT_HOME)"
        raise DataError(
            f"Dataset {entry.name!r} ({entry.repo_id}) cannot be opened {where}: {type(err).__name__}: {err}".rstrip(
                "."
            )
            + "."
        ) from None


@cache
def video_backend(requested: str) -> str:
    """The requested decoder, or PyAV (one warning per process, no traceback) when torchcodec cannot load."""
    if requested != "torchcodec":
        return requested
    try:
        import torchcodec.decoders  # noqa: F401  # loads FFmpeg's shared libraries
    except (ImportError, OSError, RuntimeError) as err:
        logger.warning("torchcodec cannot be loaded ({}); decoding video with pyav instead.", type(err).__name__)
        return "pyav"
    return requested


def split_episodes(total: int, eval_episodes: int, name: str) -> tuple[list[int], list[int]]:
    """Train on all but the last ``eval_episodes`` episodes; hold those out."""
    if eval_episodes >= total:
        raise DataError(
            f"Dataset {name!r} has {total} episodes, so eval-episodes={eval_episodes} leaves none to train on; "
            f"expected eval-episodes < {total}."
        )
    return list(range(total - eval_episodes)), list(range(total - eval_episodes, total))


def _make(
    entry: DatasetEntry, policy_cfg: PreTrainedConfig, run: RunConfig, episodes: list[int] | None
) -> LeRobotDataset:
    root = entry.local_root()
    backend = video_backend(run.video_backend)
    cfg = TrainPipelineConfig(
        dataset=DatasetConfig(
            repo_id=entry.repo_id,
            root=str(root) if root else None,
            episodes=episodes,
            revision=entry.revision,
            video_backend=backend,
        ),
        policy=policy_cfg,
        tolerance_s=run.tolerance_s,
    )
    dataset = make_dataset(cfg)
    attach_frame_cache(dataset, entry.name, run.frame_cache_gb, default_cache_root(), backend)
    return dataset


def open_split(
    entry: DatasetEntry,
    meta: LeRobotDatasetMetadata,
    policy_cfg: PreTrainedConfig,
    run: RunConfig,
    held_out: list[int] | None = None,
) -> DatasetSplit:
    """A client's dataset: training episodes and the held-out ones (``held_out``: the ones this
    client held out earlier in the run, kept whatever the owner recorded since)."""
    if held_out is None:
        train_eps, eval_eps = split_episodes(meta.total_episodes, run.eval_episodes, entry.name)
    else:
        eval_eps = held_out
        train_eps = [e for e in range(meta.total_episodes) if e not in set(held_out)]
    return DatasetSplit(entry, meta, _make(entry, policy_cfg, run, train_eps), _make(entry, policy_cfg, run, eval_eps))


def with_training(split: DatasetSplit, meta: LeRobotDatasetMetadata, policy_cfg: PreTrainedConfig, run: RunConfig,
                  episodes: list[int]) -> DatasetSplit:  # fmt: skip
    """``split`` training on ``episodes`` of its dataset as ``meta`` now describes it, holding out
    the same episodes as before (a grown dataset: zk0.federation.growth)."""
    return DatasetSplit(split.entry, meta, _make(split.entry, policy_cfg, run, episodes), split.evaluation)


def open_evaluation(
    entry: DatasetEntry, meta: LeRobotDatasetMetadata, policy_cfg: PreTrainedConfig, run: RunConfig
) -> DatasetSplit:
    """The server's evaluation dataset: every episode is held out."""
    return DatasetSplit(entry, meta, None, _make(entry, policy_cfg, run, None))


MAX_WORKERS = 8


def available_cpus() -> float:
    """CPUs this client may use: its Ray share in simulation, its SuperNode's share of the machine
    (``--cpus``, or divided among the SuperNodes running: zk0.common.machine), else the process's CPU affinity."""
    try:
        import ray

        if ray.is_initialized():
            return float(ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0))
    except (ImportError, RuntimeError):
        pass
    on_supernode = machine.cpus_now()
    return float(on_supernode if on_supernode is not None else machine.affinity())


def loader_workers(run: RunConfig) -> int:
    """``num-workers``, or for -1 one worker per available CPU beyond the training loop's own (<= 8)."""
    if run.num_workers >= 0:
        return run.num_workers
    return max(0, min(MAX_WORKERS, int(available_cpus()) - 1))


def worker_options(run: RunConfig) -> dict:
    """DataLoader worker settings: spawned (as lerobot's train script does: the apps' processes run
    threads, and forking them is unsafe) and persistent across rounds."""
    workers = loader_workers(run)
    if workers == 0:
        return {"num_workers": 0}
    return {"num_workers": workers, "multiprocessing_context": "spawn", "persistent_workers": True}


def train_loader(dataset: LeRobotDataset, run: RunConfig, device: torch.device) -> DataLoader:
    """Shuffled, episode-aware batches for local training (lerobot's sampler, seeded)."""
    sampler = EpisodeAwareSampler(
        dataset.meta.episodes["dataset_from_index"],
        dataset.meta.episodes["dataset_to_index"],
        episode_indices_to_use=dataset.episodes,
        shuffle=True,
        seed=run.seed,
        absolute_to_relative_idx=dataset.absolute_to_relative_idx,
    )
    return DataLoader(
        dataset,
        batch_size=run.batch_size,
        sampler=sampler,
        **worker_options(run),
        pin_memory=device.type == "cuda",
        drop_last=False,
    )


def eval_loader(dataset: LeRobotDataset, run: RunConfig) -> DataLoader:
    """Held-out frames in a fixed order, so every round evaluates the same batches."""
    return DataLoader(dataset, batch_size=run.batch_size, shuffle=False, **worker_options(run))


def prepare_batch(batch: dict, camera_keys: list[str], task: str | None, device: torch.device) -> dict:
    """uint8 frames to float [0, 1], as lerobot's train script does, and the registry's task text.

    The frames travel to the device first, as uint8 from the loader's pinned memory: a quarter
    of the bytes of float32, and the conversion runs on the GPU instead of the training loop's
    CPU. (IEEE division is exactly rounded on both, so the values are lerobot's.)
    """
    for key in camera_keys:
        if key in batch and batch[key].dtype == torch.uint8:
            batch[key] = batch[key].to(device, non_blocking=True).to(dtype=torch.float32) / 255.0
    if task is not None:
        batch["task"] = [task] * len(batch["task"])
    return batch
