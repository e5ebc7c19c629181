"""LoRA on the wire: lerobot's own PEFT wrapping of SmolVLA, what travels, what a checkpoint holds.

With ``peft = "lora"`` every party wraps the same pretrained SmolVLA with lerobot's
``wrap_with_peft`` (SmolVLA's default targets: the action expert's q/v projections and the
state/action/time projections), seeded, so the frozen base and the adapters' initialisation
are bit-identical everywhere and the backbone fingerprint covers both. By default
(``lora-full-modules``) the five small state/action/time projections are trained in full
instead of adapted (PEFT's ``modules_to_save``): docs/learning.md measured them closing
LoRA's gap to training in full at ~4 MB per round for full-size SmolVLA. The trainable
tensors, and so what travels and what FedProx anchors, are the adapters and those projections:

- ``lora-average = "b"`` (the default): A stays frozen at its shared seeded start and only B
  is trained and averaged. The average of the clients' ``B_i·A`` is then exactly
  ``mean(B_i)·A``, what FedAvg sends back, and half the adapter bytes travel.
- ``lora-average = "ab"``: A and B are both trained and averaged separately; ``mean(B_i)·mean(A_i)``
  is not ``mean(B_i·A_i)``, so the global update is only approximately the clients' average.

docs/learning.md has the measurements behind the default. A checkpoint holds the adapters
merged into the base (``merge_and_unload``): a plain lerobot pretrained-model directory that
``SmolVLAPolicy.from_pretrained`` and ``lerobot-rollout`` load as they load any other, with
the adapters (and the projections trained in full) in PEFT's own format under ``adapter/``
(what a resumed run continues from).
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch
from lerobot.policies import PreTrainedPolicy
from peft import PeftModel, set_peft_model_state_dict
from safetensors.torch import load_file

from zk0.common.errors import Zk0Error
from zk0.config import LORA_FULL_MODULES, RunConfig

ADAPTER_DIR = "adapter"  # inside a checkpoint: PEFT's adapter_config.json + adapter_model.safetensors


def full_modules(run: RunConfig) -> list[str]:
    """The module names ``lora-full-modules`` lists."""
    return [name.strip() for name in run.lora_full_modules.split(",") if name.strip()]


def overrides(run: RunConfig) -> dict:
    """lerobot's ``PeftConfig`` fields (as its ``--peft.*`` options) from the run config."""
    full = full_modules(run)
    return {
        "method_type": "lora",
        "r": run.lora_rank,
        "lora_alpha": run.lora_alpha,
        "target_modules": run.lora_targets or None,  # None: SmolVLA's own defaults
        "full_training_modules": full or None,
    }


def wrap(policy: PreTrainedPolicy, run: RunConfig) -> PeftModel:
    """The policy wrapped with lerobot's PEFT support, identically on every party (seeded)."""
    torch.manual_seed(run.seed)
    try:
        adapted = policy.wrap_with_peft(peft_cli_overrides=overrides(run))
    except ValueError as err:  # lerobot's and PEFT's refusals of a config (no module matches the targets, ...)
        raise Zk0Error(f"lerobot cannot add LoRA adapters with these lora-* keys: {err}") from None
    _check_full_modules(adapted, full_modules(run))
    if run.lora_average == "b":
        for name, param in adapted.named_parameters():
            if ".lora_A." in name:
                param.requires_grad_(False)
    return adapted


def _check_full_modules(adapted: PeftModel, names: list[str]) -> None:
    """PEFT silently skips a ``modules_to_save`` name that matches no module: refuse it instead, or a
    misspelt name would leave that module frozen while the user believes it trains."""
    trained = [name for name, _ in adapted.named_parameters() if ".modules_to_save." in name]
    for module in names:
        if not any(f".{module}.modules_to_save." in name for name in trained):
            raise Zk0Error(
                f"Run-config key 'lora-full-modules' names {module!r}, which matches no module of this SmolVLA; "
                f"expected module names such as {LORA_FULL_MODULES!r}."
            )


def is_adapted(policy: torch.nn.Module) -> bool:
    return isinstance(policy, PeftModel)


def merged(policy: PreTrainedPolicy | PeftModel) -> PreTrainedPolicy:
    """A plain SmolVLA with the adapters merged into its weights (a copy: ``policy`` keeps training)."""
    if not is_adapted(policy):
        return policy
    plain = copy.deepcopy(policy).merge_and_unload()
    plain.config.use_peft = False  # a merged checkpoint loads as a plain policy, with no adapter to find
    return plain


def load_adapter(policy: PeftModel, checkpoint: Path) -> None:
    """Put a checkpoint's adapters (``<checkpoint>/adapter``) into ``policy`` in place."""
    weights = checkpoint / ADAPTER_DIR / "adapter_model.safetensors"
    if not weights.is_file():
        raise Zk0Error(
            f"Checkpoint {str(checkpoint)!r} has no LoRA adapter ({ADAPTER_DIR}/adapter_model.safetensors), "
            "so a peft='lora' run cannot continue from it."
        )
    result = set_peft_model_state_dict(policy, load_file(weights))
    missing = [key for key in result.missing_keys if "lora_" in key]
    if result.unexpected_keys or missing:
        raise Zk0Error(
            f"The adapter in {str(checkpoint)!r} does not fit this run's LoRA keys (missing {missing[:2]}, "
            f"unexpected {list(result.unexpected_keys)[:2]}); resume with the lora-* values it was trained with."
        )
