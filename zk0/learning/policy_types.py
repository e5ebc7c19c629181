"""The lerobot policy types zk0 federates, and the config of a fresh one of each.

``policy`` (run config) names the type a fresh model is built as; ``model`` its size: ``tiny``
for a CPU, ``full-size`` for lerobot's own defaults. A checkpoint given as ``model`` brings its
own type and config (zk0.learning.policy reads them).

- **smolvla:** SmolVLA on an offline SmolVLM-shaped backbone with random weights, frozen as
  SmolVLA freezes it (zk0.data.assets generates it; ``tiny``, ``tiny-128`` and ``full-size``).
- **act:** lerobot's ACT, trained end to end, its ResNet-18 included. lerobot's default starts
  that ResNet from torchvision's ImageNet weights, a download no machine here can make, so it
  starts from random weights (``pretrained_backbone_weights = None``). ACT sees each dataset's
  frames at their own size, so ``tiny-128`` (the simulator preset's SmolVLA size) is its
  ``tiny`` too. ``tiny`` keeps ACT's
  architecture at a width and depth one CPU step can afford (the transformer is small next to
  the ResNet, which dominates the step; docs/performance.md); ``full-size`` is lerobot's default.
- **diffusion:** lerobot's Diffusion Policy, its ResNet-18 trained from scratch with GroupNorm
  (as the paper trains it without ImageNet weights, which no machine here can fetch) and a
  spatial-softmax keypoint head. It looks at the last ``n_obs_steps`` = 2 observations and plays
  ``chunk-size`` actions of each predicted ``horizon``. ``tiny`` shares one ResNet between the
  cameras, narrows the U-Net
  (``down_dims`` 64-128-256: 5 M parameters against lerobot's 255 M; 16 M in all) and denoises in
  10 DDIM steps instead of 100 DDPM ones; ``full-size`` is lerobot's default U-Net and scheduler.
  Both warm the learning rate up over a tenth of the run at most (lerobot's 500 steps would
  take a short federation's every step). ``tiny-128`` is its ``tiny`` too, as for ACT.
"""

from __future__ import annotations

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
from transformers import AutoConfig

from zk0.config import RunConfig
from zk0.data.assets import OFFLINE_BACKBONES, ensure_backbone

# torch.compile mode for `compile = true`: lerobot's default, max-autotune, spends minutes
# benchmarking kernels in every new process; "default" measured 0.157 s/step at batch 64 on an
# H100 against 0.288 s eager (docs/performance.md).
COMPILE_MODE = "default"

# ACT at ``model = "tiny"``: a quarter of the default width, two encoder layers and lerobot's one
# decoder layer (the VAE stays: its KL term is part of ACT's loss).
TINY_ACT = {"dim_model": 128, "dim_feedforward": 512, "n_heads": 4, "n_encoder_layers": 2, "n_vae_encoder_layers": 2}

# What a lerobot policy type is called where a sentence names it.
NAMES = {"smolvla": "SmolVLA", "act": "ACT", "diffusion": "Diffusion Policy"}
# What a robot's computer installs to run each (the SO arms' motor SDK and the policy's own extra).
LEROBOT_EXTRAS = {"smolvla": "feetech,smolvla", "act": "feetech", "diffusion": "feetech,diffusion"}

# Diffusion Policy at ``model = "tiny"``: a narrow U-Net, denoised in few DDIM steps on a CPU.
TINY_DIFFUSION = {"down_dims": (64, 128, 256), "diffusion_step_embed_dim": 64, "noise_scheduler_type": "DDIM",
                  "num_inference_steps": 10, "use_separate_rgb_encoder_per_camera": False}  # fmt: skip
DIFFUSION_OBS_STEPS = 2  # the paper's and lerobot's: the last two observations


def name_of(cfg: PreTrainedConfig) -> str:
    """A policy config's type as people write it (SmolVLA, ACT)."""
    return NAMES.get(cfg.type, cfg.type)


def fresh_config(run: RunConfig, device: torch.device) -> PreTrainedConfig:
    """The config of a fresh ``run.policy`` of size ``run.model``, on ``device``."""
    return {"smolvla": smolvla_config, "act": act_config, "diffusion": diffusion_config}[run.policy](run, device)


def smolvla_config(run: RunConfig, device: torch.device) -> SmolVLAConfig:
    """SmolVLA on the offline backbone of ``run.model``, at that backbone's image size."""
    backbone = ensure_backbone(kind=OFFLINE_BACKBONES[run.model])
    image_size = AutoConfig.from_pretrained(backbone).vision_config.image_size
    return SmolVLAConfig(
        vlm_model_name=str(backbone),
        load_vlm_weights=False,
        resize_imgs_with_padding=(image_size, image_size),
        chunk_size=run.chunk_size,
        n_action_steps=run.chunk_size,
        optimizer_lr=run.lr,
        device=device.type,
        push_to_hub=False,
        compile_model=run.compile,
        compile_mode=COMPILE_MODE,
    )


def act_config(run: RunConfig, device: torch.device) -> ACTConfig:
    """ACT from random weights, its backbone at the run's learning rate (lerobot's 1e-5 for the
    backbone assumes ImageNet features to keep; these are learnt from the owners' frames)."""
    return ACTConfig(
        pretrained_backbone_weights=None,
        chunk_size=run.chunk_size,
        n_action_steps=run.chunk_size,
        optimizer_lr=run.lr,
        optimizer_lr_backbone=run.lr,
        device=device.type,
        push_to_hub=False,
        **({} if run.model == "full-size" else TINY_ACT),
    )


def diffusion_config(run: RunConfig, device: torch.device) -> DiffusionConfig:
    """Diffusion Policy from random weights: ``chunk-size`` actions played of each prediction,
    whose horizon is the shortest the U-Net's downsampling allows that holds them."""
    tiny = {} if run.model == "full-size" else TINY_DIFFUSION
    stages = 2 ** len(tiny.get("down_dims", DiffusionConfig.down_dims))
    needed = run.chunk_size + DIFFUSION_OBS_STEPS - 1  # the chunk starts at the latest observation
    return DiffusionConfig(
        pretrained_backbone_weights=None,
        use_group_norm=True,
        n_obs_steps=DIFFUSION_OBS_STEPS,
        horizon=-(-needed // stages) * stages,
        n_action_steps=run.chunk_size,
        optimizer_lr=run.lr,
        scheduler_warmup_steps=min(DiffusionConfig.scheduler_warmup_steps, run.total_steps // 10),
        device=device.type,
        push_to_hub=False,
        **tiny,
    )
