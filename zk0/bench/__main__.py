"""``python -m zk0.bench <name> [options]``: run one benchmark; each prints a table."""

from __future__ import annotations

import signal
import sys

from zk0.bench import (
    container,
    deployment,
    exchange,
    gpu,
    hetero,
    inputs,
    learning,
    memory,
    owners,
    policies,
    privacy,
    robust,
    robustness,
    round,
    scale,
    secagg,
    sim,
    sim_learning,
    soak,
    step,
    study,
)
from zk0.common.errors import Zk0Error
from zk0.data.assets import ensure_all

# Each module has ``main(argv)`` and ``build_parser()``.
BENCHMARKS = {
    "learning": learning,
    "study": study,
    "robust": robust,
    "robustness": robustness,
    "exchange": exchange,
    "step": step,
    "round": round,
    "memory": memory,
    "deployment": deployment,
    "gpu": gpu,
    "sim": sim,
    "inputs": inputs,
    "sim-learning": sim_learning,
    "hetero": hetero,
    "scale": scale,
    "owners": owners,
    "soak": soak,
    "privacy": privacy,
    "secagg": secagg,
    "container": container,
    "policies": policies,
}


def usage() -> str:
    """Each benchmark with the first line of its module's docstring."""
    lines = [f"  {name:<13} {module.__doc__.strip().splitlines()[0]}" for name, module in BENCHMARKS.items()]
    return "usage: python -m zk0.bench <benchmark> [options] (--help for its options)\n\n" + "\n".join(lines)


def main(argv: list[str]) -> int:
    if argv[:1] in (["-h"], ["--help"]):
        print(usage())
        return 0
    if not argv or argv[0] not in BENCHMARKS:
        got = repr(argv[0]) if argv else "nothing"
        print(f"python -m zk0.bench: got {got}; expected one of {', '.join(BENCHMARKS)} (see --help).", file=sys.stderr)
        return 2
    if not set(argv[1:]) & {"-h", "--help"}:
        ensure_all()  # the offline backbone and datasets: generated here, once, never by opening them
    try:
        return BENCHMARKS[argv[0]].main(argv[1:])
    except Zk0Error as err:  # a combination zk0 refuses (ACT with LoRA): its sentence, not a traceback
        print(f"python -m zk0.bench {argv[0]}: {err}", file=sys.stderr)
        return 2


def stop_on_sigterm() -> None:
    """``kill`` (SIGTERM) ends a benchmark as Ctrl-C does, its clean-up run: the federation it started
    (its SuperLink, the ServerApp, Ray's actors) stops with it. Killed without, a study left its
    federation training on alone, two actors at 100% of both cores."""
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


if __name__ == "__main__":
    stop_on_sigterm()
    sys.exit(main(sys.argv[1:]))
