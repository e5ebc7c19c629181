"""Open a registry entry as LeRobotDatasets through lerobot's ``make_dataset``.

The last ``eval-episodes`` episodes are held out for evaluation and never trained on.
Batches come from a plain ``DataLoader`` over lerobot's ``EpisodeAwareSampler``, as in
lerobot's own training script; ``prepare_batch`` does what that script does between
the loader and the preprocessor (uint8 frames to [0, 1]) plus the registry's task text.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets import EpisodeAwareSampler
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.factory import make_dataset
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from torch.utils.data import DataLoader

from zk0.config import RunConfig
from zk0.errors import Zk0Error
from zk0.registry import DatasetEntry


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
    root = entry.local_root()
    return LeRobotDatasetMetadata(entry.repo_id, root=root, revision=entry.revision)


def split_episodes(total: int, eval_episodes: int, name: str) -> tuple[list[int], list[int]]:
    """Train on all but the last ``eval_episodes`` episodes; hold those out."""
    if eval_episodes >= total:
        raise DataError(
            f"Dataset {name!r} has {total} episodes, so eval-episodes={eval_episodes} leaves none to train on; "
            f"expected eval-episodes < {total}."
        )
    return list(range(total - eval_episodes)), list(range(total - eval_episodes, total))


def _make(entry: DatasetEntry, policy_cfg: PreTrainedConfig, episodes: list[int] | None) -> LeRobotDataset:
    root = entry.local_root()
    cfg = TrainPipelineConfig(
        dataset=DatasetConfig(
            repo_id=entry.repo_id,
            root=str(root) if root else None,
            episodes=episodes,
            revision=entry.revision,
        ),
        policy=policy_cfg,
    )
    return make_dataset(cfg)


def open_split(
    entry: DatasetEntry, meta: LeRobotDatasetMetadata, policy_cfg: PreTrainedConfig, run: RunConfig
) -> DatasetSplit:
    """A client's dataset: training episodes and the held-out ones."""
    train_eps, eval_eps = split_episodes(meta.total_episodes, run.eval_episodes, entry.name)
    return DatasetSplit(entry, meta, _make(entry, policy_cfg, train_eps), _make(entry, policy_cfg, eval_eps))


def open_evaluation(entry: DatasetEntry, meta: LeRobotDatasetMetadata, policy_cfg: PreTrainedConfig) -> DatasetSplit:
    """The server's evaluation dataset: every episode is held out."""
    return DatasetSplit(entry, meta, None, _make(entry, policy_cfg, None))


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
        num_workers=run.num_workers,
        persistent_workers=run.num_workers > 0,
        pin_memory=device.type == "cuda",
        drop_last=False,
    )


def eval_loader(dataset: LeRobotDataset, run: RunConfig) -> DataLoader:
    """Held-out frames in a fixed order, so every round evaluates the same batches."""
    return DataLoader(dataset, batch_size=run.batch_size, shuffle=False, num_workers=run.num_workers)


def prepare_batch(batch: dict, camera_keys: list[str], task: str | None) -> dict:
    """uint8 frames to float [0, 1] (as lerobot's train script does) and the registry's task text."""
    for key in camera_keys:
        if key in batch and batch[key].dtype == torch.uint8:
            batch[key] = batch[key].to(dtype=torch.float32) / 255.0
    if task is not None:
        batch["task"] = [task] * len(batch["task"])
    return batch
