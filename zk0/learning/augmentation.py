"""lerobot's image augmentation on the owner's machine (``image-transforms``).

An owner's room is lit, framed and furnished its own way, and a policy trained only on frames as
recorded fails in a room darker than any it saw. lerobot ships the remedy its own training uses,
``ImageTransforms`` (``lerobot-train --dataset.image_transforms.enable=true``): a random subset of
brightness, contrast, saturation, hue, sharpness and a small affine shift, drawn for every frame.
zk0 applies it to each training batch after the frames reach the device, so the decoded-frame
cache keeps the frames as recorded and evaluation (offline and in closed loop) never sees it.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from lerobot.transforms.transforms import ImageTransforms, ImageTransformsConfig

from zk0.config import RunConfig


def frame_transforms(run: RunConfig) -> ImageTransforms | None:
    """lerobot's transforms as the run config sets them (None: ``image-transforms`` off): lerobot's
    defaults, at most ``image-transforms-max`` per frame, brightness within 1 +- ``image-transforms-brightness``."""
    if not run.image_transforms:
        return None
    cfg = ImageTransformsConfig(enable=True, max_num_transforms=run.image_transforms_max)
    spread = run.image_transforms_brightness
    cfg.tfs["brightness"] = replace(cfg.tfs["brightness"], kwargs={"brightness": (1.0 - spread, 1.0 + spread)})
    return ImageTransforms(cfg)


def augment(batch: dict, camera_keys: list[str], transforms: ImageTransforms) -> dict:
    """Each frame of each camera transformed on its own draw, as lerobot's dataset does per item
    (one call on the whole batch would give every frame the same jitter)."""
    for key in camera_keys:
        if key in batch:
            batch[key] = torch.stack([transforms(frame) for frame in batch[key]]).clamp_(0.0, 1.0)
    return batch
