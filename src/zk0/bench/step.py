"""Step benchmark: the zk0 client's local step against lerobot's plain ``update_policy``.

One process, one policy, one batch size; the three loops run in interleaved blocks so that
machine noise hits them alike:

- ``zk0``: the client's own ``LocalTrainer.fit`` (its DataLoader with video decoding,
  preprocessing, FedProx hooks, ``update_policy``);
- ``plain+data``: lerobot's loop as its train script runs it, on the same DataLoader;
- ``plain``: ``update_policy`` on one pre-loaded, preprocessed batch (the compute floor).

The ratio zk0 / plain is what a GPU client should keep near 1.

    python -m zk0.bench step [--full-size] [--batch-size 8] [--steps 10] [--blocks 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from lerobot.scripts.lerobot_train import update_policy
from lerobot.utils.logging_utils import AverageMeter, MetricsTracker

from zk0.config import RunConfig
from zk0.data import open_metadata, open_split, prepare_batch, train_loader
from zk0.policy import build_policy
from zk0.registry import load_registry
from zk0.training import LocalTrainer, peak_memory


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _tracker(trainer: LocalTrainer) -> MetricsTracker:
    meters = {name: AverageMeter(name) for name in ("loss", "grad_norm", "lr", "update_s", "dataloading_s")}
    return MetricsTracker(trainer.run.batch_size, 1, 1, meters)


def plain_steps(trainer: LocalTrainer, steps: int, batch: dict | None) -> float:
    """lerobot's loop: next batch (unless pre-loaded), uint8 -> float, preprocessor, update_policy."""
    bundle, tracker = trainer.bundle, _tracker(trainer)
    batches = iter(trainer.loader) if batch is None else None
    _sync(bundle.device)
    start = time.perf_counter()
    for _ in range(steps):
        ready = batch
        if ready is None:
            ready = bundle.preprocessor(prepare_batch(next(batches), trainer.split.meta.camera_keys, None))
        update_policy(
            tracker, bundle.policy, ready, trainer.optimizer, trainer.grad_clip_norm,
            accelerator=trainer.accelerator, lr_scheduler=trainer.scheduler,
        )  # fmt: skip
    _sync(bundle.device)
    return (time.perf_counter() - start) / steps


def zk0_steps(trainer: LocalTrainer, steps: int) -> float:
    _sync(trainer.bundle.device)
    start = time.perf_counter()
    trainer.fit(steps, mu=0.01, global_step=0)
    _sync(trainer.bundle.device)
    return (time.perf_counter() - start) / steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--full-size", action="store_true", help="SmolVLM2-500M-shaped backbone (random weights)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--steps", type=int, default=10, help="steps per block")
    parser.add_argument("--blocks", type=int, default=3, help="interleaved blocks per loop")
    parser.add_argument("--num-workers", type=int, default=0)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)

    registry = load_registry()
    entry = registry.clients[0]
    run = RunConfig(
        model="full-size" if args.full_size else "tiny",
        batch_size=args.batch_size,
        num_workers=args.num_workers,
        device=args.device,
        num_server_rounds=1,
        local_steps=args.steps * args.blocks * 3 + 10,
    )
    meta = open_metadata(entry)
    bundle = build_policy(run, meta, entry, registry.model_cameras())
    split = open_split(entry, meta, bundle.policy.config, run)
    trainer = LocalTrainer(bundle, split, train_loader(split.train, run, bundle.device), run)
    preloaded = bundle.preprocessor(prepare_batch(next(iter(trainer.loader)), meta.camera_keys, None))
    zk0_steps(trainer, 2)  # warm-up: first-call allocations, decoder start-up
    plain_steps(trainer, 2, preloaded)

    times: dict[str, list[float]] = {"zk0": [], "plain+data": [], "plain": []}
    for _ in range(args.blocks):
        times["zk0"].append(zk0_steps(trainer, args.steps))
        times["plain+data"].append(plain_steps(trainer, args.steps, None))
        times["plain"].append(plain_steps(trainer, args.steps, preloaded))
    median = {name: statistics.median(values) for name, values in times.items()}

    print(f"model {run.model} on {bundle.device}, batch {run.batch_size}, {args.blocks} blocks x {args.steps} steps")
    print(f"{'loop':>11} {'s/step':>9} {'samples/s':>10} {'vs plain':>9}")
    for name, value in median.items():
        print(f"{name:>11} {value:>9.4f} {run.batch_size / value:>10.1f} {value / median['plain']:>9.3f}")
    memory = peak_memory(bundle.device)
    print(f"peak GPU {memory['peak-gpu-gib']:.2f} GiB, host RSS {memory['host-rss-gib']:.2f} GiB")
    if args.json:
        Path(args.json).write_text(
            json.dumps({"device": str(bundle.device), "median-s": median, "times": times, **memory})
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
