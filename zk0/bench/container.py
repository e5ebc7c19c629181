"""Container: the zk0 image's size, its rebuild after a one-line change, and the quick run in it against outside it.

What a user pays for ``./train.sh --docker``, measured with the engine ``./train.sh`` picks
(``ZK0_ENGINE`` chooses; the image ``zk0`` must exist, as ``./train.sh --docker`` or
``docker build -t zk0 .`` leaves it):

- the image's size;
- the rebuild after a one-line change to zk0's code: a copy of the project's tracked files with
  one comment added to ``zk0/__init__.py``, built as ./test.sh builds the image (podman, on the
  Debian base it makes: scripts/setup.sh, zk0_build_image), whose layer cache holds everything
  before the project's own layer; then untagged;
- the quick run (``./train.sh``, 1 round, 2 steps) outside and inside the container, each after
  its set-up (one unmeasured run of each first: .venv, the offline assets, the cache volume),
  alternated ``--runs`` times: the time to its first round's line and to its end, and the ratio.

    python -m zk0.bench container [--runs 2] [--json FILE]
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from zk0.bench.client import write_json
from zk0.common.errors import OneSentenceParser, positive
from zk0.data.registry import PROJECT_ROOT

TRAIN = str(PROJECT_ROOT / "train.sh")


def engine() -> str:
    """The engine ``./train.sh --docker`` uses (the first word of the command it prints)."""
    done = subprocess.run([TRAIN, "--docker", "--print"], capture_output=True, text=True, check=True)
    return done.stdout.split()[0]


def image_size_gb(tool: str) -> float:
    done = subprocess.run([tool, "image", "inspect", "zk0"], capture_output=True, text=True, check=True)
    return json.loads(done.stdout)[0]["Size"] / 1e9


def rebuild_s() -> float:
    """Seconds to build a copy of the project whose only change is one line of zk0's code."""
    files = subprocess.run(["git", "ls-files"], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True)
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "zk0"
        for name in files.stdout.splitlines():
            if (PROJECT_ROOT / name).is_file():
                (copy / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(PROJECT_ROOT / name, copy / name)
        with (copy / "zk0" / "__init__.py").open("a") as init:
            init.write(f"# a one-line change, {time.time()}\n")
        build = ["bash", "-c", 'source scripts/setup.sh && zk0_build_image "$0" zk0-rebuild', str(copy)]
        start = time.perf_counter()
        done = subprocess.run(build, cwd=PROJECT_ROOT, capture_output=True, text=True, check=False)
        seconds = time.perf_counter() - start
    subprocess.run(["podman", "rmi", "zk0-rebuild"], capture_output=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"bench container: the rebuild failed: {done.stderr.strip().splitlines()[-1]}")
    return seconds


def quick_run(*flags: str) -> dict[str, float]:
    """``./train.sh [flags]`` with its outputs in a folder removed afterwards: seconds to the
    first round's line and to the end."""
    folder = f"bench-container-{os.getpid()}"
    inside = "--docker" in flags
    out = f"/workspace/outputs/{folder}" if inside else str(PROJECT_ROOT / "outputs" / folder)
    start = time.perf_counter()
    proc = subprocess.Popen(
        [TRAIN, *flags, "-r", f"output-dir='{out}'"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    first_round = None
    for line in proc.stdout:
        if first_round is None and line.startswith("[zk0] Round 1/"):
            first_round = time.perf_counter() - start
    proc.wait()
    total = time.perf_counter() - start
    shutil.rmtree(PROJECT_ROOT / "outputs" / folder, ignore_errors=True)
    if proc.returncode != 0 or first_round is None:
        raise SystemExit(f"bench container: ./train.sh {' '.join(flags)} failed (exit {proc.returncode}).")
    return {"first-round-s": first_round, "total-s": total}


def build_parser() -> OneSentenceParser:
    parser = OneSentenceParser(prog="python -m zk0.bench container", description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=positive(int), default=2, help="timed quick runs of each (default 2)")
    parser.add_argument("--json", default=None)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    tool = engine()
    figures: dict = {"engine": tool, "image-gb": round(image_size_gb(tool), 2)}
    figures["rebuild-after-one-line-s"] = round(rebuild_s(), 1)
    print(f"Image zk0 ({tool}): {figures['image-gb']} GB; rebuilt after a one-line change in {figures['rebuild-after-one-line-s']} s")
    quick_run()  # set-up and assets outside; the cache volume inside
    quick_run("--docker")
    runs: dict[str, list[dict]] = {"outside": [], "inside": []}
    for _ in range(args.runs):
        runs["outside"].append(quick_run())
        runs["inside"].append(quick_run("--docker"))
    for key in ("first-round-s", "total-s"):
        outside = statistics.median(r[key] for r in runs["outside"])
        inside = statistics.median(r[key] for r in runs["inside"])
        figures[key] = {"outside": round(outside, 1), "inside": round(inside, 1), "ratio": round(inside / outside, 2)}
        print(f"Quick run, {key}: {outside:.1f} s outside, {inside:.1f} s in the container ({inside / outside:.2f}x)")
    figures["runs"] = runs
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
