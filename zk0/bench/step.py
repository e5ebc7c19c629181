"""Step benchmark: the zk0 client's local step against lerobot's plain ``update_policy``.

One process, one policy, one batch size; the three loops run in interleaved blocks so that
machine noise hits them alike:

- ``zk0``: the client's own ``LocalTrainer.fit`` (its DataLoader over the decoded-frame
  cache, frames to the device as uint8, preprocessing, FedProx hooks, ``update_policy``);
- ``plain+data``: lerobot's loop as its train script runs it, over lerobot's own data path
  (a DataLoader that decodes video for every sample, frames made float on the host);
- ``plain``: ``update_policy`` on one pre-loaded, preprocessed batch (the compute floor);
- ``zk0 full`` (with ``--peft lora``): the client trained in full from the same starting weights,
  so the LoRA client's step compares with the full one's in the same run.

The ratio zk0 / plain is what a GPU client should keep near 1. ``--dataset synth-so100-480p``
decodes an SO-100's real camera size (480x640, two cameras) instead of the tiny test videos.

    python -m zk0.bench step [--full-size] [--dataset NAME] [--batch-size 8] [--steps 10] [--blocks 3]
                             [--num-workers 0] [--frame-cache-gb 20] [--peft lora] [--json out.json]
"""

from __future__ import annotations

import itertools
import statistics
import sys
import time
from dataclasses import replace

import torch
from lerobot.scripts.lerobot_train import update_policy
from lerobot.utils.logging_utils import MetricsTracker
from torch.utils.data import DataLoader

from zk0.bench.client import add_client_options, bench_client, write_json
from zk0.common.errors import OneSentenceParser
from zk0.data.loaders import loader_workers, open_split, train_loader
from zk0.learning.training import LocalTrainer, metrics_tracker, peak_memory


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _tracker(trainer: LocalTrainer) -> MetricsTracker:
    return metrics_tracker(trainer.run.batch_size, 1, 1)


def lerobot_batch(batch: dict, cameras: list[str]) -> dict:
    """What lerobot's train script does between its DataLoader and its preprocessor."""
    for key in cameras:
        if key in batch and batch[key].dtype == torch.uint8:
            batch[key] = batch[key].to(dtype=torch.float32) / 255.0
    return batch


def plain_steps(trainer: LocalTrainer, steps: int, loader: DataLoader | None, batch: dict | None = None) -> float:
    """lerobot's loop: next batch from ``loader`` (or the pre-loaded one), preprocessor, update_policy."""
    bundle, tracker = trainer.bundle, _tracker(trainer)
    batches = itertools.chain.from_iterable(itertools.repeat(loader)) if loader is not None else None  # epochs
    _sync(bundle.device)
    start = time.perf_counter()
    for _ in range(steps):
        ready = batch
        if ready is None:
            ready = bundle.preprocessor(lerobot_batch(next(batches), trainer.split.meta.camera_keys))
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


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench step", description=__doc__.split("\n\n")[0])
    add_client_options(parser)
    parser.add_argument("--steps", type=int, default=10, help="steps per block")
    parser.add_argument("--blocks", type=int, default=3, help="interleaved blocks per loop")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    trainer, _, entry = bench_client(args, local_steps=args.steps * args.blocks * 3 + 10)
    # With --peft lora, the same starting weights trained in full, interleaved with the LoRA client.
    full = bench_client(args, args.steps * args.blocks + 10, peft="none")[0] if args.peft == "lora" else None
    run, bundle, meta = trainer.run, trainer.bundle, trainer.split.meta
    decoding = open_split(entry, meta, bundle.policy.config, replace(run, frame_cache_gb=0)).train
    lerobot_loader = train_loader(decoding, run, bundle.device)
    preloaded = bundle.preprocessor(lerobot_batch(next(iter(lerobot_loader)), meta.camera_keys))
    zk0_steps(trainer, 2)  # warm-up: first-call allocations, decoder and worker start-up
    plain_steps(trainer, 2, lerobot_loader)
    if full:
        zk0_steps(full, 2)

    times: dict[str, list[float]] = {"zk0": [], "plain+data": [], "plain": []} | ({"zk0 full": []} if full else {})
    for _ in range(args.blocks):
        times["zk0"].append(zk0_steps(trainer, args.steps))
        if full:
            times["zk0 full"].append(zk0_steps(full, args.steps))
        times["plain+data"].append(plain_steps(trainer, args.steps, lerobot_loader))
        times["plain"].append(plain_steps(trainer, args.steps, None, preloaded))
    median = {name: statistics.median(values) for name, values in times.items()}

    print(
        f"model {run.model} (peft {run.peft}) on {bundle.device}, dataset {entry.name}, batch {run.batch_size}, "
        f"{args.blocks} blocks x {args.steps} steps, {loader_workers(run)} DataLoader workers"
    )
    print(f"{'loop':>11} {'s/step':>9} {'samples/s':>10} {'vs plain':>9}")
    for name, value in median.items():
        print(f"{name:>11} {value:>9.4f} {run.batch_size / value:>10.1f} {value / median['plain']:>9.3f}")
    if full:
        print(f"LoRA step / full-trainable step (zk0's client, same weights): {median['zk0'] / median['zk0 full']:.3f}")
    memory = peak_memory(bundle.device)
    print(f"peak GPU {memory['peak-gpu-gib']:.2f} GiB, host RSS {memory['host-rss-gib']:.2f} GiB")
    figures = {"device": str(bundle.device), "dataset": entry.name, "median-s": median, "times": times}
    write_json(args.json, {**figures, **memory})
    return 0


if __name__ == "__main__":
    sys.exit(main())
