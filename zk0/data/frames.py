"""The decoded-frame cache: each episode's video decoded once, in order, and kept as uint8.

A training step asks lerobot's dataset for random frames, and each one costs a seek to the
preceding keyframe and a decode forward from there. On a small model that is most of a
step; on a GPU it is what starves the model (docs/performance.md). Local training visits
every frame many times, so a client decodes each episode of each camera once, with
lerobot's own decoder and at exactly the timestamps of the episode's rows, and keeps the
frames as one uint8 ``.npy`` per episode and camera under the zk0 cache. The dataset then
reads frames from there, memory-mapped (DataLoader workers share the page cache).

The cache is keyed by the dataset's video files (names, sizes, modification times) and
the decoder, so re-recorded videos get a new one and it outlives runs. A query the cache
cannot answer exactly (a timestamp that is not one of the episode's rows, a depth camera)
or an episode whose video failed to decode while building) is decoded from the video, as
lerobot would, so a broken video still costs batches, not the client.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from filelock import FileLock
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.video_utils import decode_video_frames
from loguru import logger

from zk0.internals import decode_videos, returns_uint8, serve_videos_from

DECODE_CHUNK = 256  # frames decoded per call while building: bounds the builder's memory
FREE_DISK_MARGIN = 1e9  # bytes left free on the cache's disk after building


@dataclass
class FrameCache:
    """Where one dataset's decoded frames live, and which timestamp is which row of an episode."""

    directory: Path
    rows: dict[int, dict[float, int]]  # episode -> {timestamp: row within the episode}
    return_uint8: bool
    stored: set[tuple[int, str]] = field(default_factory=set)  # (episode, camera) decoded into the cache
    _maps: dict[tuple[int, str], np.ndarray] = field(default_factory=dict, repr=False)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_maps": {}}  # memory maps are reopened in each DataLoader worker

    def path(self, episode: int, camera: str) -> Path:
        return self.directory / camera / f"episode_{episode:06d}.npy"

    def frames(self, episode: int, camera: str, timestamps: list[float]) -> torch.Tensor | None:
        """The cached frames at ``timestamps`` (lerobot's layout and dtype), or None if any is unknown."""
        key, rows = (episode, camera), self.rows.get(episode)
        if key not in self.stored or rows is None or any(ts not in rows for ts in timestamps):
            return None
        if key not in self._maps:
            self._maps[key] = np.load(self.path(episode, camera), mmap_mode="r")
        frames = torch.from_numpy(np.ascontiguousarray(self._maps[key][[rows[ts] for ts in timestamps]]))
        if not self.return_uint8:
            frames = frames.type(torch.float32) / 255  # as lerobot's decoders convert
        return frames.squeeze(0)

    def query_videos(self, reader: DatasetReader, query_timestamps: dict[str, list[float]], ep_idx: int) -> dict:
        """Stands in for ``DatasetReader._query_videos``: cached cameras from disk, the rest decoded."""
        found = {key: self.frames(ep_idx, key, ts) for key, ts in query_timestamps.items()}
        missing = {key: query_timestamps[key] for key, frames in found.items() if frames is None}
        if missing:
            found.update(decode_videos(reader, missing, ep_idx))
        return found


def cache_key(dataset: LeRobotDataset, backend: str) -> str:
    """A digest of what the decoded frames depend on: the video files and the decoder."""
    videos = {str(p.relative_to(dataset.root)): p.stat() for p in (dataset.root / "videos").rglob("*.mp4")}
    described = {
        "repo_id": dataset.repo_id,
        "backend": backend,
        "features": {key: dataset.meta.features[key] for key in dataset.meta.video_keys},
        "videos": sorted((name, st.st_size, st.st_mtime_ns) for name, st in videos.items()),
    }
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=str).encode()).hexdigest()[:16]


def episode_rows(dataset: LeRobotDataset) -> dict[int, np.ndarray]:
    """Each episode's row timestamps in row order, read straight from the Arrow columns."""
    table = dataset.hf_dataset.data
    episodes = table.column("episode_index").to_numpy()
    order = np.argsort(table.column("index").to_numpy(), kind="stable")
    timestamps = table.column("timestamp").to_numpy()[order]
    episodes = episodes[order]
    return {int(ep): timestamps[episodes == ep] for ep in np.unique(episodes)}


def cached_cameras(dataset: LeRobotDataset) -> tuple[str, ...]:
    """The colour video cameras (depth maps keep lerobot's own decoding)."""
    return tuple(key for key in dataset.meta.video_keys if key not in dataset.meta.depth_keys)


def frame_bytes(dataset: LeRobotDataset, camera: str, rows: int) -> int:
    """Bytes ``rows`` decoded uint8 frames of ``camera`` take."""
    return int(np.prod(dataset.meta.features[camera]["shape"])) * rows


def build_episode(
    dataset: LeRobotDataset, cache: FrameCache, episode: int, camera: str, timestamps: np.ndarray, backend: str
) -> None:
    """Decode one episode of one camera at its rows' timestamps and store the frames atomically."""
    start = dataset.meta.episodes[episode][f"videos/{camera}/from_timestamp"]
    video = dataset.root / dataset.meta.get_video_file_path(episode, camera)
    shifted = [start + ts for ts in timestamps.tolist()]
    chunks = [
        decode_video_frames(
            video, shifted[i : i + DECODE_CHUNK], dataset.tolerance_s, backend, return_uint8=True
        ).numpy()
        for i in range(0, len(shifted), DECODE_CHUNK)
    ]
    target = cache.path(episode, camera)
    target.parent.mkdir(parents=True, exist_ok=True)
    partial_file = target.with_suffix(".partial.npy")
    try:
        np.save(partial_file, np.concatenate(chunks))
    except BaseException:  # a full disk: no half file left behind
        partial_file.unlink(missing_ok=True)
        raise
    os.replace(partial_file, target)


def attach_frame_cache(
    dataset: LeRobotDataset, name: str, budget_gb: float, root: Path, backend: str
) -> FrameCache | None:
    """Build (or reuse) ``dataset``'s decoded-frame cache under ``root`` and read frames from it.

    Returns None, and leaves lerobot's decoding in place, when the cache is off
    (``budget_gb`` 0), larger than ``budget_gb``, or larger than the free disk.
    """
    cameras = cached_cameras(dataset)
    if budget_gb <= 0 or not cameras:
        return None
    rows = episode_rows(dataset)
    needed = sum(frame_bytes(dataset, cam, len(ts)) for ts in rows.values() for cam in cameras)
    if needed > budget_gb * 1e9:
        logger.warning(
            "Dataset {!r}: its decoded frames need {:.1f} GB, more than frame-cache-gb={}; decoding video "
            "for every batch instead (raise frame-cache-gb to cache them).", name, needed / 1e9, budget_gb
        )  # fmt: skip
        return None
    directory = root / "frames" / dataset.repo_id.replace("/", "--") / cache_key(dataset, backend)
    directory.mkdir(parents=True, exist_ok=True)
    cache = FrameCache(
        directory, {ep: dict(zip(ts.tolist(), range(len(ts)), strict=True)) for ep, ts in rows.items()},
        returns_uint8(dataset),
    )  # fmt: skip
    with FileLock(str(directory / ".lock")):
        cache.stored = {(ep, cam) for ep in rows for cam in cameras if cache.path(ep, cam).exists()}
        todo = [(ep, cam) for ep in rows for cam in cameras if (ep, cam) not in cache.stored]
        to_write = sum(frame_bytes(dataset, cam, len(rows[ep])) for ep, cam in todo)
        free = shutil.disk_usage(directory).free
        if to_write > free - FREE_DISK_MARGIN:
            logger.warning(
                "Dataset {!r}: its decoded frames need {:.1f} GB more but {} has {:.1f} GB free; decoding video "
                "for every batch instead.", name, to_write / 1e9, directory, free / 1e9
            )  # fmt: skip
            return None
        started = time.perf_counter()
        for ep, cam in todo:
            try:
                build_episode(dataset, cache, ep, cam, rows[ep], backend)
            except OSError as err:
                if err.errno != errno.ENOSPC:
                    raise
                logger.warning(
                    "Dataset {!r}: the disk holding {} filled up while caching its frames; the rest are read "
                    "from the video.", name, directory
                )  # fmt: skip
                break
            except Exception as err:  # noqa: BLE001  # the batches that need it will report it
                logger.warning("Dataset {!r}: {} of episode {} did not decode ({}); it is read from the video.",
                               name, cam, ep, err)  # fmt: skip
                continue
            cache.stored.add((ep, cam))
    built = sum(key in cache.stored for key in todo)
    if built:
        logger.info(
            "Dataset {!r}: decoded {} episode videos into the frame cache under {} in {:.1f} s.",
            name, built, directory, time.perf_counter() - started,
        )  # fmt: skip
    serve_videos_from(dataset, cache.query_videos)
    return cache
