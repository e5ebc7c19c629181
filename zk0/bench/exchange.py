"""Exchange benchmark: what one client sends and receives per round, and what it costs to handle.

Builds the global policy exactly as the ServerApp does (SmolVLA, or ACT with ``--policy act``;
tiny, or with ``--full-size`` SmolVLA's SmolVLM2-500M-shaped backbone or lerobot's default ACT,
offline with random weights: realistic sizes without the Hub),
then for each wire dtype measures the bytes per client per direction, the client's encode
time, and the server's decode + FedAvg time for ``--clients`` updates (Flower's own
``aggregate_arrayrecords``), against the whole state dict the seed project sent.

With ``--peft lora`` the model is first saved as a pretrained starting point (lerobot adapts only
pretrained weights) and the bytes of LoRA's adapters, in both averaging modes and with SmolVLA's
small projections trained in full next to them, are measured next to the same weights trained in full.

    python -m zk0.bench exchange [--policy smolvla] [--full-size] [--peft lora] [--clients 4] [--repeat 3]
        [--json out.json]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch
from flwr.app import ArrayRecord, MetricRecord, RecordDict
from flwr.serverapp.strategy.strategy_utils import aggregate_arrayrecords

from zk0.bench.client import starting_checkpoint
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import POLICIES, RunConfig
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry
from zk0.federation.wire import decode, encode
from zk0.learning.policy import build_policy, trainable_tensors


def best_of(repeat: int, fn) -> float:
    """Fastest of ``repeat`` timed calls, in seconds (the least disturbed by the rest of the machine)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def measure(tensors: dict[str, torch.Tensor], wire_dtype: str, clients: int, repeat: int) -> dict:
    update = encode(tensors, wire_dtype)
    replies = [
        RecordDict(
            {"arrays": ArrayRecord(decode(update, wire_dtype)), "metrics": MetricRecord({"num-examples": 1 + i})}
        )
        for i in range(clients)
    ]
    return {
        "wire-dtype": wire_dtype,
        "tensors": len(update),
        "bytes-per-direction": update.count_bytes(),
        "encode-s": best_of(repeat, lambda: encode(tensors, wire_dtype)),
        "decode-s": best_of(repeat, lambda: decode(update, wire_dtype)),
        "aggregate-s": best_of(repeat, lambda: aggregate_arrayrecords(replies, "num-examples")),
    }


def variants(args) -> list[tuple[str, RunConfig]]:
    """What to measure: the trainable weights, and with ``--peft lora`` the same starting weights
    trained in full next to LoRA's two averaging modes and adapters with SmolVLA's small
    projections trained in full (zk0.learning.adapters)."""
    model = "full-size" if args.full_size else "tiny"
    if args.peft == "none":
        return [("full", RunConfig(model=model, device="cpu", policy=args.policy))]
    start = starting_checkpoint(model)
    lora = {"peft": "lora", "lora_rank": args.lora_rank}
    return [
        ("full", RunConfig(model=start, device="cpu")),
        ("lora b", RunConfig(model=start, device="cpu", lora_average="b", lora_full_modules="", **lora)),
        ("lora ab", RunConfig(model=start, device="cpu", lora_average="ab", lora_full_modules="", **lora)),
        ("lora b+proj", RunConfig(model=start, device="cpu", lora_average="b", **lora)),  # zk0's default
    ]


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench exchange", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", choices=POLICIES, default="smolvla", help="the lerobot policy type")
    parser.add_argument("--full-size", action="store_true", help="SmolVLA's SmolVLM2-500M-shaped backbone, or lerobot's default ACT (random weights)")
    parser.add_argument("--peft", choices=["none", "lora"], default="none", help="lora: also LoRA's adapters")
    parser.add_argument("--lora-rank", type=positive(int), default=RunConfig.lora_rank)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.peft == "lora" and args.policy != "smolvla":
        parser.error(f"--peft lora adapts SmolVLA, and --policy is {args.policy}; expected --peft none")

    registry = load_registry()
    entry = registry.get("synth-so100-eval")
    totals, rows = [], []
    for label, run in variants(args):
        started = time.perf_counter()
        bundle = build_policy(run, open_metadata(entry), entry, registry.model_cameras())
        build_s = time.perf_counter() - started
        tensors = trainable_tensors(bundle)
        state = bundle.policy.state_dict()
        totals.append(
            {
                "variant": label,
                "model": run.model,
                "parameters": sum(p.numel() for p in bundle.policy.parameters()),
                "trainable": sum(t.numel() for t in tensors.values()),
                "trainable-tensors": len(tensors),
                "state-dict-tensors": len(state),
                "state-dict-bytes-fp32": sum(t.numel() * 4 for t in state.values()),
                "build-s": build_s,
            }
        )
        rows += [
            {"variant": label, **measure(tensors, dtype, args.clients, args.repeat)}
            for dtype in ("float32", "bfloat16")
        ]
        del bundle, state, tensors

    for total in totals:
        print(
            f"{total['variant']:>8}: {total['parameters']:,} parameters, {total['trainable']:,} trainable "
            f"({total['trainable-tensors']} of {total['state-dict-tensors']} tensors); built in {total['build-s']:.1f} s"
        )
    print(
        f"model {totals[0]['model']}; the whole state dict in fp32: {totals[0]['state-dict-bytes-fp32'] / 1e6:,.1f} MB"
    )
    print(
        f"{'variant':>8} {'wire':>9} {'MB/direction':>13} {'encode s':>9} {'decode s':>9} {f'FedAvg x{args.clients} s':>13}"
    )
    for row in rows:
        print(
            f"{row['variant']:>8} {row['wire-dtype']:>9} {row['bytes-per-direction'] / 1e6:>13.3f} {row['encode-s']:>9.3f} "
            f"{row['decode-s']:>9.3f} {row['aggregate-s']:>13.3f}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({"model": totals[0], "variants": totals, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
