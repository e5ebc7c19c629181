"""Memory benchmark: what one client holds on the GPU and the host, phase by phase.

Builds a client the way the ClientApp does and reads its memory after each phase: the
policy built, the dataset opened (and its frame cache built), the first optimizer step
(AdamW's moments appear), and ``--steps`` more steps. GPU figures are PyTorch's allocator
(allocated now, and the peak since the start); host figures are resident memory of this
process plus its DataLoader workers (pages they share are counted once per process).

    python -m zk0.bench memory [--full-size] [--dataset NAME] [--batch-size 8] [--steps 5]
                               [--num-workers 0] [--device auto] [--json out.json]
"""

from __future__ import annotations

import sys

import psutil
import torch

from zk0.bench.client import add_client_options, bench_client, write_json
from zk0.common.errors import OneSentenceParser

GIB = 2**30


def snapshot(phase: str, device: torch.device) -> dict:
    """Memory now: GPU allocated and peak (GiB, 0 on CPU), host RSS of this process and its workers."""
    me = psutil.Process()
    workers = sum(child.memory_info().rss for child in me.children(recursive=True))
    cuda = device.type == "cuda"
    return {
        "phase": phase,
        "gpu-allocated-gib": torch.cuda.memory_allocated(device) / GIB if cuda else 0.0,
        "gpu-peak-gib": torch.cuda.max_memory_allocated(device) / GIB if cuda else 0.0,
        "host-rss-gib": me.memory_info().rss / GIB,
        "workers-rss-gib": workers / GIB,
    }


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench memory", description=__doc__.split("\n\n")[0])
    add_client_options(parser)
    parser.add_argument("--steps", type=int, default=5, help="steps after the first")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    baseline = snapshot("python + torch + lerobot imported", torch.device("cpu"))
    trainer, _, entry = bench_client(args, local_steps=args.steps + 1)
    device = trainer.bundle.device
    phases = [baseline, snapshot("policy, processors, dataset, optimizer built", device)]
    trainer.fit(1, mu=0.01, global_step=0)
    phases.append(snapshot("after the first step (optimizer state)", device))
    trainer.fit(args.steps, mu=0.01, global_step=1)
    phases.append(snapshot(f"after {args.steps} more steps", device))

    print(f"model {trainer.run.model} on {device}, dataset {entry.name}, batch {trainer.run.batch_size}")
    print(f"{'phase':<46} {'GPU now':>8} {'GPU peak':>9} {'host RSS':>9} {'workers':>8}   (GiB)")
    for row in phases:
        print(
            f"{row['phase']:<46} {row['gpu-allocated-gib']:>8.2f} {row['gpu-peak-gib']:>9.2f} "
            f"{row['host-rss-gib']:>9.2f} {row['workers-rss-gib']:>8.2f}"
        )
    write_json(args.json, {"device": str(device), "dataset": entry.name, "phases": phases})
    return 0


if __name__ == "__main__":
    sys.exit(main())
