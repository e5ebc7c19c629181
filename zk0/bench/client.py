"""One client built the way the ClientApp builds it, for the in-process benchmarks (step, memory),
and the pretrained starting point a LoRA benchmark needs when the model is an offline one."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from zk0.artifacts.run_folder import save_checkpoint
from zk0.common.cache import default_cache_root
from zk0.config import OFFLINE_MODELS, POLICIES, RunConfig, from_run_config
from zk0.data.assets import ensure_dataset
from zk0.data.assets.datasets import SPECS
from zk0.data.loaders import open_metadata
from zk0.data.registry import DatasetEntry, Registry, load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import build_policy
from zk0.learning.training import LocalTrainer


def add_client_options(parser: argparse.ArgumentParser) -> None:
    """The options both in-process benchmarks take: model, dataset, batch, data path, device, output."""
    parser.add_argument("--policy", choices=POLICIES, default="smolvla", help="the lerobot policy type (run-config policy)")
    parser.add_argument("--full-size", action="store_true", help="SmolVLA's SmolVLM2-500M-shaped backbone or lerobot's default ACT (random weights)")
    parser.add_argument("--dataset", help="a registry name or synth-so100-480p (default: the first client's)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--num-workers", type=int, default=0, help="DataLoader workers (-1 = the CPUs minus one)")
    parser.add_argument("--frame-cache-gb", type=float, default=RunConfig.frame_cache_gb, help="0 = decode always")
    parser.add_argument("--device", default="auto")
    parser.add_argument(
        "--compile", action="store_true", help="torch.compile the training forward (run-config compile)"
    )
    parser.add_argument(
        "--peft", choices=["none", "lora"], default="none", help="lora: LoRA adapters (run-config peft)"
    )
    parser.add_argument("--json", help="also write the figures to this JSON file")


def starting_checkpoint(model: str) -> str:
    """A pretrained-model directory to adapt with LoRA: ``model`` itself, or for an offline model
    (random weights, which lerobot will not adapt) that model saved once as a checkpoint under
    ``$ZK0_CACHE/bench`` — the same weights every benchmark run, so their figures compare."""
    if model not in OFFLINE_MODELS:
        return model
    root = default_cache_root() / "bench" / f"{model}-start"
    checkpoint = root / "models" / "checkpoint_round_0"
    if not (checkpoint / "model.safetensors").is_file():
        registry = load_registry()
        entry = registry.clients[0]
        bundle = build_policy(
            RunConfig(model=model, device="cpu"), open_metadata(entry), entry, registry.model_cameras()
        )
        save_checkpoint(bundle, root, 0, {})
    return str(checkpoint)


def bench_entry(registry: Registry, name: str | None) -> DatasetEntry:
    """A registry entry, or a synthetic dataset the registry does not list (the 480p one)."""
    if name is None:
        return registry.clients[0]
    if name in SPECS and name not in {entry.name for entry in registry.entries}:
        targets = registry.model_cameras()  # observation.images.<target>, sorted
        cameras = {src: dst.rsplit(".", 1)[-1] for src, dst in zip(SPECS[name].cameras, targets, strict=False)}
        ensure_dataset(name)  # benchmark-only: not among what `zk0 assets` generates by default
        return DatasetEntry(SPECS[name].repo_id, name, synthetic=True, cameras=cameras)
    return registry.get(name)


def bench_client(
    args: argparse.Namespace, local_steps: int, peft: str | None = None
) -> tuple[LocalTrainer, Registry, DatasetEntry]:
    """A client's ``LocalTrainer`` (policy, processors, dataset split, loader, optimizer) for ``args``.

    With ``--peft lora`` the model is the LoRA starting checkpoint, also when ``peft`` overrides
    ``--peft`` (``"none"``: the same weights trained in full, to compare with).
    """
    registry = load_registry()
    entry = bench_entry(registry, args.dataset)
    model = "full-size" if args.full_size else "tiny"
    run = RunConfig(
        model=starting_checkpoint(model) if args.peft == "lora" and args.policy == "smolvla" else model,
        policy=args.policy,
        peft=peft or args.peft,
        batch_size=args.batch_size,
        num_workers=args.num_workers,
        frame_cache_gb=args.frame_cache_gb,
        device=args.device,
        compile=args.compile,
        num_server_rounds=1,
        local_steps=local_steps,
    )
    from_run_config(run.to_flat())  # a combination a run would refuse (ACT with LoRA) is refused here too
    return build_client(run, entry, registry.model_cameras()).trainer, registry, entry


def write_json(path: str | None, figures: dict) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(figures, indent=2))
