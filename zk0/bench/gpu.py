"""GPU benchmark: what a robot owner's GPU time goes to, in one command and one JSON.

Runs the other benchmarks, each in its own process (each starts with an empty GPU):

- ``step``, eager and with ``--compile``: the client's local step at ``--batch-size`` on
  ``synth-so100-480p`` (two 480x640 cameras, frame cache, DataLoader workers chosen from the
  machine) against plain ``update_policy`` on a pre-loaded batch, and their ratio;
- ``memory`` at ``--batch-size`` and at a quarter of it: peak GPU memory, and the largest batch
  that fits in a 24 GiB consumer GPU on the straight line through the two;
- ``deployment``: a steady round of ``--local-steps`` through a loopback Deployment Engine (one
  TLS SuperNode; no Ray), split into local steps and everything else;
- ``exchange``: bytes per client and direction, encode/decode/aggregate times.

Needs lerobot, flwr and their light dependencies on a machine that has PyTorch with CUDA.

    python -m zk0.bench gpu [--batch-size 64] [--local-steps 200] [--model full-size] [--json gpu.json]
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from zk0.bench.client import write_json
from zk0.errors import OneSentenceParser

CONSUMER_GPU_GIB = 24.0


def run_benchmark(name: str, args: list[str], folder: Path, timeout: float) -> dict | None:
    """``python -m zk0.bench <name> ... --json``; its figures, or None (with its output's end) on failure."""
    out = folder / f"{name}-{len(list(folder.iterdir()))}.json"
    started = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "zk0.bench", name, *args, "--json", str(out)],
            capture_output=True, text=True, timeout=timeout, check=False,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        print(f"bench.gpu: {name} {' '.join(args)} ran past {timeout:.0f} s; skipped.", file=sys.stderr)
        return None
    print(f"  {name} {' '.join(args)}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    if done.returncode != 0 or not out.is_file():
        print(done.stdout[-1500:] + done.stderr[-2500:], file=sys.stderr)
        print(f"bench.gpu: {name} failed (exit {done.returncode}); its output is above.", file=sys.stderr)
        return None
    return json.loads(out.read_text())


def largest_batch(small: tuple[int, float], large: tuple[int, float], budget_gib: float) -> int:
    """The batch whose peak memory reaches ``budget_gib`` on the line through two (batch, peak) points."""
    (b1, m1), (b2, m2) = small, large
    per_sample = (m2 - m1) / (b2 - b1)
    return int((budget_gib - m1) / per_sample + b1) if per_sample > 0 else b2


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench gpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="full-size", choices=["full-size", "tiny"])
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--local-steps", type=int, default=200, help="local steps of the deployment round")
    parser.add_argument("--steps", type=int, default=10, help="steps per block of the step benchmark")
    parser.add_argument("--dataset", default="synth-so100-480p", help="the step and memory benchmarks' dataset")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.batch_size < 4:
        parser.error(f"--batch-size got {args.batch_size}; expected at least 4 (memory is also measured at a quarter).")

    size = ["--full-size"] if args.model == "full-size" else []
    client = [*size, "--dataset", args.dataset, "--num-workers", "-1"]
    quarter = max(1, args.batch_size // 4)
    figures: dict = {"settings": vars(args)}
    with tempfile.TemporaryDirectory(prefix="zk0-bench-gpu-") as tmp:
        folder = Path(tmp)
        steps = [*client, "--batch-size", str(args.batch_size), "--steps", str(args.steps), "--blocks", "3"]
        figures["step-eager"] = run_benchmark("step", steps, folder, 300)
        figures["step-compiled"] = run_benchmark("step", [*steps, "--compile"], folder, 420)
        for batch in (quarter, args.batch_size):
            figures[f"memory-{batch}"] = run_benchmark("memory", [*client, "--batch-size", str(batch)], folder, 240)
        figures["deployment"] = run_benchmark(
            "deployment",
            ["--model", args.model, "--no-simulation", "--clients", "1", "--rounds", "2", "--local-steps",
             str(args.local_steps), "--batch-size", str(args.batch_size), "--num-workers", "-1"],
            folder, 600,
        )  # fmt: skip
        figures["exchange"] = run_benchmark("exchange", [*size, "--clients", "2", "--repeat", "1"], folder, 240)

    print(f"\nmodel {args.model}, batch {args.batch_size}")
    for mode in ("eager", "compiled"):
        step = figures[f"step-{mode}"]
        if step:
            median = step["median-s"]
            print(
                f"step ({mode}): client {median['zk0']:.3f} s ({args.batch_size / median['zk0']:.0f} samples/s), "
                f"plain pre-loaded {median['plain']:.3f} s; client / plain = {median['zk0'] / median['plain']:.2f}"
            )
    peaks = {
        b: figures[f"memory-{b}"]["phases"][-1]["gpu-peak-gib"]
        for b in (quarter, args.batch_size)
        if figures[f"memory-{b}"]
    }
    if len(peaks) == 2 and peaks[args.batch_size] == 0:
        print("peak GPU memory: no GPU here (0 GiB); no largest batch to estimate")
    elif len(peaks) == 2:
        fits = largest_batch((quarter, peaks[quarter]), (args.batch_size, peaks[args.batch_size]), CONSUMER_GPU_GIB)
        figures["largest-batch-24gib"] = fits
        print(
            f"peak GPU memory: {peaks[args.batch_size]:.2f} GiB at batch {args.batch_size}; largest batch in 24 GiB ~{fits}"
        )
    deployment = figures["deployment"]
    if deployment:
        d = deployment["deployment"]
        print(
            f"deployment round: {d['steady-round-s']:.1f} s, local steps {d['local-steps-s']:.1f} s, "
            f"fixed cost {d['fixed-cost-per-round-s']:.1f} s ({100 * d['fixed-cost-per-round-s'] / d['steady-round-s']:.1f}%)"
        )
    exchange = figures["exchange"]
    if exchange:
        for row in exchange["rows"]:
            print(
                f"exchange {row['wire-dtype']}: {row['bytes-per-direction'] / 1e6:.1f} MB per client and direction, "
                f"encode {row['encode-s']:.2f} s, decode {row['decode-s']:.2f} s, aggregate {row['aggregate-s']:.2f} s"
            )
    write_json(args.json, figures)
    return 0 if all(v is not None for v in figures.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
