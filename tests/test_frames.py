"""The decoded-frame cache gives exactly lerobot's samples, is reused, and steps aside when it must."""

from __future__ import annotations

import os
import pickle

import pytest
import torch
from lerobot.datasets import dataset_reader
from loguru import logger

from zk0.common.cache import default_cache_root
from zk0.config import RunConfig
from zk0.data.frames import attach_frame_cache, cache_key
from zk0.data.loaders import _make, open_metadata
from zk0.internals import video_query
from zk0.learning.policy import build_policy

DECODE_EVERY_BATCH = RunConfig(frame_cache_gb=0)


@pytest.fixture(scope="module")
def policy_cfg(registry):
    entry = registry.clients[0]
    return build_policy(DECODE_EVERY_BATCH, open_metadata(entry), entry, registry.model_cameras()).policy.config


def _no_video(*args, **kwargs):
    raise AssertionError("a cached sample was decoded from the video")


def _warnings():
    messages: list[str] = []
    handler = logger.add(messages.append, level="WARNING", format="{message}")
    return messages, handler


def test_cached_samples_equal_lerobots_decoded_samples(registry, policy_cfg, monkeypatch):
    entry = registry.clients[0]
    decoded = _make(entry, policy_cfg, DECODE_EVERY_BATCH, None)
    cached = _make(entry, policy_cfg, RunConfig(), None)
    cache = video_query(cached).func.__self__  # the FrameCache serving the dataset
    assert len(cache.stored) == len(decoded.meta.camera_keys) * decoded.num_episodes
    assert cache.directory.is_relative_to(default_cache_root() / "frames")
    in_worker = pickle.loads(pickle.dumps(cached))  # what a spawned DataLoader worker receives
    for index in range(len(decoded)):
        expected = decoded[index]
        with monkeypatch.context() as patch:  # the cached datasets must not touch the video
            patch.setattr(dataset_reader, "decode_video_frames", _no_video)
            samples = (cached[index], in_worker[index])
        for got in samples:
            assert got.keys() == expected.keys()
            for key, value in expected.items():
                if isinstance(value, torch.Tensor):
                    assert value.dtype == got[key].dtype and torch.equal(value, got[key]), (index, key)
                else:
                    assert value == got[key], (index, key)


def test_the_cache_is_reused_and_rebuilt_when_a_video_changes(registry, policy_cfg, tmp_path):
    entry = registry.clients[0]
    dataset = _make(entry, policy_cfg, DECODE_EVERY_BATCH, None)
    first = attach_frame_cache(dataset, entry.name, 1.0, tmp_path, "pyav")
    files = sorted(first.directory.rglob("*.npy"))
    assert len(files) == len(first.stored) > 0
    stamps = [f.stat().st_mtime_ns for f in files]
    again = attach_frame_cache(dataset, entry.name, 1.0, tmp_path, "pyav")
    assert again.directory == first.directory
    assert [f.stat().st_mtime_ns for f in files] == stamps, "a second client reuses the frames, never re-decodes"
    video = next((dataset.root / "videos").rglob("*.mp4"))
    before = cache_key(dataset, "pyav")
    os.utime(video, ns=(video.stat().st_atime_ns, video.stat().st_mtime_ns + 1))
    try:
        assert cache_key(dataset, "pyav") != before, "a re-recorded video must not be served stale frames"
    finally:
        os.utime(video, ns=(video.stat().st_atime_ns, video.stat().st_mtime_ns - 1))
    assert cache_key(dataset, "torchcodec") != before, "frames decoded by another decoder are kept apart"


def test_a_dataset_over_the_budget_is_decoded_every_batch(registry, policy_cfg, tmp_path):
    entry = registry.clients[0]
    dataset = _make(entry, policy_cfg, DECODE_EVERY_BATCH, None)
    messages, handler = _warnings()
    try:
        assert attach_frame_cache(dataset, entry.name, 1e-4, tmp_path, "pyav") is None
    finally:
        logger.remove(handler)
    assert "more than frame-cache-gb=0.0001" in messages[0] and not (tmp_path / "frames").exists()
    assert dataset[0]["observation.images.front"].dtype == torch.uint8
