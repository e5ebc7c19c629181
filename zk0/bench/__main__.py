"""``python -m zk0.bench <name> [options]``: run one benchmark; each prints a table."""

from __future__ import annotations

import sys

from zk0.bench import deployment, exchange, gpu, learning, memory, round, step

BENCHMARKS = {
    "learning": learning.main,
    "exchange": exchange.main,
    "step": step.main,
    "round": round.main,
    "memory": memory.main,
    "deployment": deployment.main,
    "gpu": gpu.main,
}


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in BENCHMARKS:
        print(
            f"usage: python -m zk0.bench {{{','.join(BENCHMARKS)}}} [options]; got {argv[:1] or 'nothing'}.",
            file=sys.stderr,
        )
        return 2
    return BENCHMARKS[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
