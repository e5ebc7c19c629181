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

    python -m zk0.bench gpu [--batch-size 64] [--local-steps 200] [--model full-size]
                            [--stages step-eager,step-compiled,...] [--time-limit S] [--json gpu.json]
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser

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
    except subprocess.TimeoutExpired as stopped:
        print(_tail(stopped.stdout, 1500) + _tail(stopped.stderr, 2500), file=sys.stderr)
        print(f"bench.gpu: {name} {' '.join(args)} ran past {timeout:.0f} s; stopped.", file=sys.stderr)
        return None
    print(f"  {name} {' '.join(args)}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    if done.returncode != 0 or not out.is_file():
        print(done.stdout[-1500:] + done.stderr[-2500:], file=sys.stderr)
        print(f"bench.gpu: {name} failed (exit {done.returncode}); its output is above.", file=sys.stderr)
        return None
    return json.loads(out.read_text())


def _tail(output: bytes | str | None, chars: int) -> str:
    """The end of a stopped child's output (bytes when the child was killed mid-line)."""
    if isinstance(output, bytes):
        output = output.decode(errors="replace")
    return (output or "")[-chars:]


def largest_batch(small: tuple[int, float], large: tuple[int, float], budget_gib: float) -> int:
    """The batch whose peak memory reaches ``budget_gib`` on the line through two (batch, peak) points."""
    (b1, m1), (b2, m2) = small, large
    per_sample = (m2 - m1) / (b2 - b1)
    return int((budget_gib - m1) / per_sample + b1) if per_sample > 0 else b2


STAGES = ("step-eager", "step-compiled", "memory", "deployment", "exchange")
MIN_STAGE_S = 60.0  # a stage given less than this would only build the model and stop


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench gpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="full-size", choices=["full-size", "tiny"])
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--local-steps", type=int, default=200, help="local steps of the deployment round")
    parser.add_argument("--steps", type=int, default=10, help="steps per block of the step benchmark")
    parser.add_argument("--dataset", default="synth-so100-480p", help="the step and memory benchmarks' dataset")
    parser.add_argument(
        "--stages", default=",".join(STAGES), help=f"which to run, in this order, comma-separated ({', '.join(STAGES)})"
    )
    parser.add_argument(
        "--time-limit", type=float, default=0.0,
        help="seconds for all stages (0: none); a stage is stopped at what is left, and one that would start "
        f"with under {MIN_STAGE_S:.0f} s left is skipped and named, so a short GPU lease still returns figures",
    )  # fmt: skip
    parser.add_argument("--json", help="also write the figures to this JSON file")
    return parser


def stage_list(parser: OneSentenceParser, text: str) -> list[str]:
    """``--stages`` as names, refused in one sentence if one is not a stage."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in STAGES]
    if unknown or not names:
        parser.error(f"--stages got {text!r}; expected a comma-separated list of {', '.join(STAGES)}")
    return names


def stage_runs(args, names: list[str]) -> list[tuple[str, str, list[str], float]]:
    """(figure key, benchmark, its arguments, its own time-out) for each named stage, in order."""
    size = ["--full-size"] if args.model == "full-size" else []
    client = [*size, "--dataset", args.dataset, "--num-workers", "-1"]
    steps = [*client, "--batch-size", str(args.batch_size), "--steps", str(args.steps), "--blocks", "3"]
    deployment = [
        "--model", args.model, "--no-simulation", "--clients", "1", "--rounds", "2", "--local-steps",
        str(args.local_steps), "--batch-size", str(args.batch_size), "--num-workers", "-1",
    ]  # fmt: skip
    quarter = max(1, args.batch_size // 4)
    runs = {
        "step-eager": [("step-eager", "step", steps, 300)],
        "step-compiled": [("step-compiled", "step", [*steps, "--compile"], 420)],
        "memory": [
            (f"memory-{batch}", "memory", [*client, "--batch-size", str(batch)], 240)
            for batch in (quarter, args.batch_size)
        ],
        "deployment": [("deployment", "deployment", deployment, 600)],
        "exchange": [("exchange", "exchange", [*size, "--clients", "2", "--repeat", "1"], 240)],
    }
    return [run for name in names for run in runs[name]]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.batch_size < 4:
        parser.error(f"--batch-size got {args.batch_size}; expected at least 4 (memory is also measured at a quarter).")
    if args.time_limit < 0:
        parser.error(f"--time-limit got {args.time_limit:g}; expected seconds >= 0 (0: no limit).")
    names = stage_list(parser, args.stages)

    quarter = max(1, args.batch_size // 4)
    figures: dict = {"settings": vars(args), "skipped": []}
    deadline = time.perf_counter() + args.time_limit if args.time_limit else float("inf")
    with tempfile.TemporaryDirectory(prefix="zk0-bench-gpu-") as tmp:
        for key, bench, bench_args, own_timeout in stage_runs(args, names):
            left = deadline - time.perf_counter()
            if left < MIN_STAGE_S:
                print(f"bench.gpu: {key} skipped: {max(left, 0):.0f} s of --time-limit left.", file=sys.stderr)
                figures["skipped"].append(key)
                continue
            figures[key] = run_benchmark(bench, bench_args, Path(tmp), min(own_timeout, left))
            write_json(args.json, figures)  # what ran so far survives a lease that ends mid-stage

    print(f"\nmodel {args.model}, batch {args.batch_size}")
    for mode in ("eager", "compiled"):
        step = figures.get(f"step-{mode}")
        if step:
            median = step["median-s"]
            print(
                f"step ({mode}): client {median['zk0']:.3f} s ({args.batch_size / median['zk0']:.0f} samples/s), "
                f"plain pre-loaded {median['plain']:.3f} s; client / plain = {median['zk0'] / median['plain']:.2f}"
            )
    peaks = {
        b: figures[f"memory-{b}"]["phases"][-1]["gpu-peak-gib"]
        for b in (quarter, args.batch_size)
        if figures.get(f"memory-{b}")
    }
    if len(peaks) == 2 and peaks[args.batch_size] == 0:
        print("peak GPU memory: no GPU here (0 GiB); no largest batch to estimate")
    elif len(peaks) == 2:
        fits = largest_batch((quarter, peaks[quarter]), (args.batch_size, peaks[args.batch_size]), CONSUMER_GPU_GIB)
        figures["largest-batch-24gib"] = fits
        print(
            f"peak GPU memory: {peaks[args.batch_size]:.2f} GiB at batch {args.batch_size}; largest batch in 24 GiB ~{fits}"
        )
    deployment = figures.get("deployment")
    if deployment:
        d = deployment["deployment"]
        print(
            f"deployment round: {d['steady-round-s']:.1f} s, local steps {d['local-steps-s']:.1f} s, "
            f"fixed cost {d['fixed-cost-per-round-s']:.1f} s ({100 * d['fixed-cost-per-round-s'] / d['steady-round-s']:.1f}%)"
        )
    exchange = figures.get("exchange")
    if exchange:
        for row in exchange["rows"]:
            print(
                f"exchange {row['wire-dtype']}: {row['bytes-per-direction'] / 1e6:.1f} MB per client and direction, "
                f"encode {row['encode-s']:.2f} s, decode {row['decode-s']:.2f} s, aggregate {row['aggregate-s']:.2f} s"
            )
    write_json(args.json, figures)
    if figures["skipped"]:
        print(f"skipped for time: {', '.join(figures['skipped'])}")
    return 0 if all(v is not None for v in figures.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
