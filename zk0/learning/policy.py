"""The policy (SmolVLA, ACT, Diffusion Policy) and its processors, built with lerobot's factories the same way on every party.

Only the trainable parameters travel between server and clients; the frozen backbone
comes from the same base (the tiny offline backbone seeded identically, or a pretrained
checkpoint), and its fingerprint travels in the config so a mismatch fails loudly. A policy
trained in full (ACT, Diffusion Policy) has no frozen part: every parameter travels, and every party starts from
the same seeded weights.
"""

from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import torch
from flwr.app import ArrayRecord
from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.policies import PreTrainedPolicy, make_policy, make_pre_post_processors
from lerobot.processor import PolicyProcessorPipeline, RenameObservationsProcessorStep, rename_stats
from lerobot.utils.feature_utils import dataset_to_policy_features

from zk0.common.cache import default_cache_root
from zk0.common.errors import Zk0Error
from zk0.config import OFFLINE_MODELS, POLICIES, RunConfig
from zk0.data.registry import DatasetEntry
from zk0.learning import adapters
from zk0.learning.policy_types import COMPILE_MODE, fresh_config, name_of


class PolicyError(Zk0Error):
    """A dataset or model that cannot feed the global policy; one sentence naming it."""


@dataclass
class PolicyBundle:
    """A policy with the processors that normalise its inputs and unnormalise its actions."""

    policy: PreTrainedPolicy  # or a PEFT model around one (zk0.learning.adapters)
    preprocessor: PolicyProcessorPipeline
    postprocessor: PolicyProcessorPipeline
    trainable_names: list[str]
    device: torch.device
    stats: dict  # the normalisation statistics the processors use, under model key names
    # Held while the policy's weights are set and used: the server's evaluation and the writer of
    # models/best, which runs while the next round's clients train, share one policy.
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA, then MPS, then CPU."""
    if name != "auto":
        return torch.device(name)
    if torch.cuda.is_available():
        return torch.device("cuda")
    if torch.backends.mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def keep_compiled_code() -> None:
    """Point torch's compile caches (inductor's FX graphs and kernels) at ``$ZK0_CACHE/inductor``.

    A SuperNode's next run, or the next simulation, then finds the compiled code instead of
    compiling again; the default cache is under /tmp, which a reboot empties.
    """
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(default_cache_root() / "inductor"))


def policy_config(run: RunConfig, device: torch.device) -> PreTrainedConfig:
    """A fresh policy's config (zk0.learning.policy_types), or a pretrained policy's own config."""
    if run.model in OFFLINE_MODELS:
        return fresh_config(run, device)
    cfg = PreTrainedConfig.from_pretrained(run.model)
    if cfg.type not in POLICIES:
        raise PolicyError(
            f"Model {run.model!r} is a lerobot policy of type {cfg.type!r}; zk0 federates the types {list(POLICIES)}."
        )
    if cfg.type != run.policy:
        raise PolicyError(
            f"Model {run.model!r} is a lerobot policy of type {cfg.type!r} and the run says policy={run.policy!r}; "
            f"set policy={cfg.type!r} to fine-tune it."
        )
    if getattr(cfg, "pretrained_backbone_weights", None):
        # ACT builds its ResNet with torchvision's ImageNet weights (a download) before the
        # checkpoint's own weights replace them: build it empty, as nothing here can download.
        cfg.pretrained_backbone_weights = None
    cfg.pretrained_path = Path(run.model) if Path(run.model).is_dir() else run.model
    cfg.optimizer_lr = run.lr
    cfg.device = device.type
    cfg.push_to_hub = False
    if hasattr(cfg, "compile_model"):
        cfg.compile_model, cfg.compile_mode = run.compile, COMPILE_MODE
    return cfg


def config_features(cfg: PreTrainedConfig) -> dict:
    """A policy config's input and output features in one dict (what its datasets must feed)."""
    return {**cfg.input_features, **cfg.output_features}


def model_features(
    meta: LeRobotDatasetMetadata, entry: DatasetEntry, model_cameras: list[str], expected: dict | None = None
) -> dict:
    """The dataset's state, action and cameras renamed onto the global model's input keys.

    Model cameras the dataset does not have are listed too (shaped like one it has): SmolVLA
    fills them with its empty-camera slots. ``expected`` (a pretrained model's features)
    fixes the state and action sizes.
    """
    features = dataset_to_policy_features(meta.features)
    rename = entry.rename_map()
    renamed = {rename.get(key, key): ft for key, ft in features.items()}
    for key in ("observation.state", "action"):
        if key not in renamed:
            raise PolicyError(f"Dataset {entry.name!r} has no {key!r} feature; the policy needs joint state and actions.")
        if expected and key in expected and tuple(expected[key].shape) != tuple(renamed[key].shape):
            raise PolicyError(
                f"Dataset {entry.name!r} has {key!r} of shape {list(renamed[key].shape)}; "
                f"the model expects {list(expected[key].shape)}."
            )
    cameras = sorted(k for k, ft in renamed.items() if ft.type is FeatureType.VISUAL and k in model_cameras)
    if not cameras:
        raise PolicyError(
            f"Dataset {entry.name!r} has no camera mapped onto the model's inputs {model_cameras}; "
            f"map one of its cameras {sorted(meta.camera_keys)} in its registry entry (cameras = {{...}})."
        )
    images = {key: renamed.get(key, renamed[cameras[0]]) for key in model_cameras}
    return {**images, "observation.state": renamed["observation.state"], "action": renamed["action"]}


def build_policy(
    run: RunConfig, meta: LeRobotDatasetMetadata, entry: DatasetEntry, registry_cameras: list[str]
) -> PolicyBundle:
    """Build the policy + processors for one dataset with lerobot's ``make_policy``/``make_pre_post_processors``,
    wrapped with LoRA adapters when the run says ``peft = "lora"`` (zk0.learning.adapters).

    The model's cameras are a pretrained policy's own image inputs, or for a fresh policy the
    registry's mapping targets; cameras this dataset lacks become SmolVLA empty-camera slots, and
    a policy without such slots (ACT) refuses the dataset in one sentence.
    """
    device = resolve_device(run.device)
    if run.compile:
        keep_compiled_code()
    cfg = policy_config(run, device)
    if cfg.pretrained_path is None:
        features = model_features(meta, entry, registry_cameras)
        cfg.input_features = {k: ft for k, ft in features.items() if ft.type is not FeatureType.ACTION}
    else:
        pretrained = config_features(cfg)
        model_cameras = sorted(k for k, ft in cfg.input_features.items() if ft.type is FeatureType.VISUAL)
        features = model_features(meta, entry, model_cameras, expected=pretrained)
    rename = entry.rename_map()
    present = {rename.get(key, key) for key in meta.camera_keys}  # what the dataset really records
    missing = sorted(k for k, ft in features.items() if ft.type is FeatureType.VISUAL and k not in present)
    if hasattr(cfg, "empty_cameras"):
        cfg.empty_cameras = len(missing)
    elif missing:
        raise PolicyError(
            f"Dataset {entry.name!r} records nothing for the model's camera input(s) {missing}, and {name_of(cfg)} has "
            f"no empty-camera slots (SmolVLA has); map one of its cameras {sorted(meta.camera_keys)} onto each in its "
            "registry entry (cameras = {...}), or federate only datasets that record every model camera."
        )
    stats = rename_stats(meta.stats, entry.rename_map())
    check_statistics(cfg, features, stats, entry)  # before the (full-size: seconds of) build
    torch.manual_seed(run.seed)  # the frozen backbone must be bit-identical on every party
    try:
        policy = make_policy(cfg, ds_meta=meta, rename_map=entry.rename_map())
    except ValueError as err:  # lerobot's checks of what a policy type takes (Diffusion: cameras of one size)
        raise PolicyError(
            f"Dataset {entry.name!r} cannot feed {name_of(cfg)} as lerobot builds it: {str(err).rstrip('.')}."
        ) from None
    if run.peft == "lora":
        policy = adapters.wrap(policy, run)  # from here on, the adapters are what trains and travels
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config,
        pretrained_path=str(cfg.pretrained_path) if cfg.pretrained_path else None,
        dataset_stats=stats,
        **_pretrained_overrides(policy.config, stats, device) if cfg.pretrained_path else {},
    )
    for step in preprocessor.steps:
        if isinstance(step, RenameObservationsProcessorStep):
            step.rename_map = entry.rename_map()
    trainable = [name for name, p in policy.named_parameters() if p.requires_grad]
    return PolicyBundle(policy, preprocessor, postprocessor, trainable, device, stats)


# The statistics each of lerobot's normalisation modes reads (lerobot.processor.normalize_processor).
STATS_READ = {
    NormalizationMode.MEAN_STD: ("mean", "std"),
    NormalizationMode.MIN_MAX: ("min", "max"),
    NormalizationMode.QUANTILES: ("q01", "q99"),
    NormalizationMode.QUANTILE10: ("q10", "q90"),
}


def check_statistics(cfg: PreTrainedConfig, features: dict, stats: dict, entry: DatasetEntry) -> None:
    """Every statistic the policy's processors normalise by, present for every feature it reads
    (``features``: the model's, as this dataset feeds them).

    lerobot's normaliser passes a feature with no statistics through unscaled, and stops at the
    first batch of one that lacks the statistic its mode needs; either way a client would train
    on what it cannot read. (SmolVLA's cameras, empty slots included, are not normalised.)"""
    for key, feature in features.items():
        mode = cfg.normalization_mapping.get(feature.type.value, NormalizationMode.IDENTITY)
        if mode not in STATS_READ:
            continue
        missing = [name for name in STATS_READ[mode] if name not in stats.get(key, {})]
        if missing:
            raise PolicyError(
                f"Dataset {entry.name!r} has no {' or '.join(missing)} statistics for {key!r}, which {name_of(cfg)} "
                f"normalises by {NormalizationMode(mode).value}; expected them in its meta/stats.json, as lerobot records them."
            )


def _pretrained_overrides(cfg: PreTrainedConfig, stats: dict, device: torch.device) -> dict:
    """Point a pretrained checkpoint's processors at this dataset's statistics and device."""
    return {
        "preprocessor_overrides": {
            "device_processor": {"device": device.type},
            "normalizer_processor": {
                "stats": stats,
                "features": config_features(cfg),
                "norm_map": cfg.normalization_mapping,
            },
        },
        "postprocessor_overrides": {
            "unnormalizer_processor": {
                "stats": stats,
                "features": cfg.output_features,
                "norm_map": cfg.normalization_mapping,
            }
        },
    }


def trainable_tensors(bundle: PolicyBundle) -> dict[str, torch.Tensor]:
    """The trainable parameters (fp32, CPU), in a fixed order. Where the policy already is fp32 on
    the CPU these are its parameters' own memory, not a copy (``snapshot`` is)."""
    params = dict(bundle.policy.named_parameters())
    return {name: params[name].detach().to("cpu", torch.float32) for name in bundle.trainable_names}


def rng_devices(bundle: PolicyBundle) -> list[torch.device]:
    """The devices whose random state ``torch.random.fork_rng`` must save for this policy (the CPU's
    always is): where its noise is drawn."""
    return [bundle.device] if bundle.device.type == "cuda" else []


def snapshot(bundle: PolicyBundle) -> dict[str, torch.Tensor]:
    """A copy of the trainable parameters (fp32, CPU) that later training leaves as it is."""
    return {name: tensor.clone() for name, tensor in trainable_tensors(bundle).items()}


def get_trainable(bundle: PolicyBundle) -> ArrayRecord:
    """The trainable parameters as an fp32 ArrayRecord: the server's master copy of the global model."""
    return ArrayRecord(trainable_tensors(bundle))


def set_trainable(bundle: PolicyBundle, arrays: ArrayRecord | dict[str, torch.Tensor]) -> None:
    """Copy global trainable parameters into the policy; names must match exactly."""
    incoming = arrays.to_torch_state_dict() if isinstance(arrays, ArrayRecord) else arrays
    if set(incoming) != set(bundle.trainable_names):
        missing = sorted(set(bundle.trainable_names) - set(incoming))[:3]
        extra = sorted(set(incoming) - set(bundle.trainable_names))[:3]
        raise PolicyError(
            f"Global arrays do not match this policy's trainable parameters (missing {missing}, extra {extra})."
        )
    params = dict(bundle.policy.named_parameters())
    for name, tensor in incoming.items():
        if tensor.shape != params[name].shape:
            raise PolicyError(
                f"Global tensor {name!r} has shape {list(tensor.shape)}, this policy's has {list(params[name].shape)}; "
                "the datasets' state/action sizes or the base model differ."
            )
    with torch.no_grad():
        for name, tensor in incoming.items():
            params[name].copy_(tensor.to(params[name].device, params[name].dtype))


def backbone_fingerprint(bundle: PolicyBundle) -> str:
    """A short hash of every frozen parameter: equal on two parties iff their backbones are equal."""
    digest = hashlib.sha256()
    for name, param in sorted(bundle.policy.named_parameters()):
        if not param.requires_grad:
            digest.update(name.encode())
            digest.update(param.detach().to("cpu", torch.float32).numpy().tobytes())
    return digest.hexdigest()[:16]
