"""Owners: does the shared model get better as more owners join?

Federations of ``--sizes`` generated sim-cube owners (one ``[tool.zk0.owners]`` table, owners 0 to
N-1, ``--demos`` demonstrations each, recorded once), each through the real app (``flwr run``,
simulated clients) with the same ``--per-round`` owners sampled a round and the same rounds and
steps: only how many different set-ups the model meets changes, not how much it trains. Once per
``--seeds`` training seed, each federation's final global model is rolled out on the same
``--sim-episodes`` seeded episodes in the server's span and in the set-ups of ``--unseen`` owners
who took part in no run (generated indices above every run's), and the personal models of owners
0 to 3 (``--personal-owners``: in every run) in their own set-ups, each the global model fine-tuned
``--personal-steps`` on the owner's own data, as ``personal-steps`` does. Each rate pools every
seed's episodes with its 95% interval, and McNemar's test compares each size with the smallest on
the same episodes; the curve is drawn in ``<output-dir>/owners.png``. Every model and rollout is
kept in ``--output-dir`` (zk0.bench.stash): the same command continues a stopped run, and sizes
or seeds run as separate commands are tabled by one more with all of them.

    python -m zk0.bench owners [--sizes 4 16 64] [--per-round 4] [--demos 10] [--rounds 20]
        [--local-steps 75] [--model tiny-128] [--lr 1e-3] [--personal-steps 300] [--seeds 42 43]
        [--unseen 4] [--personal-owners 4] [--sim-episodes 100] [--episode-length 300] [--output-dir outputs/bench-owners] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from matplotlib.figure import Figure

from zk0.artifacts.logs import native_output_to
from zk0.bench.client import write_json
from zk0.bench.models import (
    JUDGED_BY_ROLLOUTS,
    SERVER,
    Weights,
    add_sim_cube_recipe,
    closed_loop_all,
    evaluation_sets,
    fine_tuned,
    generate,
    kept_federation,
)
from zk0.bench.stash import Stash
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import RunConfig
from zk0.data.registry import load_registry
from zk0.federation.client import build_client
from zk0.learning.rates import mcnemar, wilson

SPAN, UNSEEN, PERSONAL = "global, server's span", "global, unseen owners", "personal, own set-ups"  # the curve's rows
SETTINGS = ("per_round", "demos", "rounds", "local_steps", "batch_size", "model", "lr", "personal_steps", "wire_dtype",
            "personal_owners")  # fmt: skip


def owners_registry(folder: Path, owners: int) -> Path:
    """A registry of ``owners`` generated sim-cube owners (and their server set)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "owners-registry.toml"
    path.write_text(f'[tool.zk0.owners]\ncount = {owners}\nkind = "sim-cube"\n')
    return path


def training_run(args: argparse.Namespace, registry: Path, seed: int) -> RunConfig:
    """The in-process models' run config (the personal models' fine-tuning): the federation's own keys."""
    return RunConfig(seed=seed, registry=str(registry), server_eval_dataset=load_registry(str(registry)).server.name,
                     num_server_rounds=args.rounds, local_steps=args.local_steps, batch_size=args.batch_size,
                     lr=args.lr, model=args.model, personal_steps=args.personal_steps)  # fmt: skip


def global_model(args: argparse.Namespace, size: int, run: RunConfig, stash: Stash, server_bundle) -> Weights:
    """The ``size``-owner federation's final global model, ``--per-round`` owners sampled a round
    (kept in ``stash``)."""
    keys = {"registry": run.registry, "server-eval-dataset": run.server_eval_dataset, "model": run.model,
            "seed": run.seed, "eval-frequency": run.num_server_rounds, "min-train-clients": args.per_round,
            "fraction-train": args.per_round / size, **JUDGED_BY_ROLLOUTS}  # fmt: skip
    return kept_federation(args, stash, size, keys, server_bundle)


def run_size(args: argparse.Namespace, size: int, seed: int, unseen: list[str]) -> dict[str, dict]:
    """One federation of ``size`` owners and the personal models of the first ``--personal-owners``
    (in every run), rolled out: {model: {column: rates}}."""
    out = Path(args.output_dir) / f"owners-{size}"
    registry_path = owners_registry(out, size)
    registry = load_registry(str(registry_path))
    run = training_run(args, registry_path, seed)
    stash = Stash(out / f"seed-{seed}", {k: vars(args)[k] for k in SETTINGS})
    started = time.perf_counter()

    def say(line: str) -> None:
        print(f"  {size} owners, seed {seed}: {line} ({time.perf_counter() - started:.0f} s)", flush=True)

    cameras = registry.model_cameras()
    sessions = [build_client(run, e, cameras, i) for i, e in enumerate(registry.clients[: args.personal_owners])]
    columns = evaluation_sets(sessions, registry, run)
    models = {"global": global_model(args, size, run, stash, columns[SERVER][0])}
    say("global model trained")
    for s in sessions:
        models[f"personal {s.index}"] = stash.weights(
            f"personal {s.index}", lambda s=s: fine_tuned(s, run, models["global"])
        )
    say("personal models trained")
    plan = {SERVER: ["global"], **{name: ["global"] for name in unseen}}
    plan |= {f"client {s.index}": [f"personal {s.index}"] for s in sessions}
    where = {name: (SERVER, name) for name in unseen}
    return closed_loop_all(
        plan, models, columns, args.sim_episodes, RunConfig.seed, say, stash, where, args.episode_length
    )


def pooled(rolled: dict[int, dict[int, dict]], size: int, where: list[tuple[str, str]]) -> list[int]:
    """Every seed's outcomes of each (model, column) in ``where`` in one list, in the same order for
    every size."""
    return [o for seed in sorted(rolled[size]) for m, c in where for o in rolled[size][seed][m][c]["outcomes"]]


def table(rolled: dict[int, dict[int, dict]], unseen: list[str], personal_owners: int) -> list[dict]:
    """Per size: the global model in the server's span and on the unseen owners, the personal models
    in their owners' own set-ups (together and each), each pooled over seeds, with McNemar's test
    against the smallest size."""
    personal = [(f"personal {i}", f"client {i}") for i in range(personal_owners)]
    groups = {
        SPAN: [("global", SERVER)],
        UNSEEN: [("global", name) for name in unseen],
        PERSONAL: personal,
        **{f"{model}, own set-up": [(model, column)] for model, column in personal},
    }
    smallest = min(rolled)
    rows = []
    for size in sorted(rolled):
        for label, where in groups.items():
            got, base = pooled(rolled, size, where), pooled(rolled, smallest, where)
            low, high = wilson(sum(got), len(got))
            rows.append({"owners": size, "model": label, "success-rate": sum(got) / len(got), "low": low,
                         "high": high, "episodes": len(got), "mcnemar-p-vs-smallest": mcnemar(got, base)})  # fmt: skip
    return rows


def chart(rows: list[dict], path: Path) -> None:
    """Success against the number of owners with its 95% intervals: the global model in the server's
    span and on the unseen owners, the personal models together (a log axis: sizes grow by factors)."""
    fig = Figure(figsize=(7, 4.5))
    axis = fig.subplots()
    for label in (SPAN, UNSEEN, PERSONAL):
        mine = [r for r in rows if r["model"] == label]
        x = [r["owners"] for r in mine]
        y = [100 * r["success-rate"] for r in mine]
        below = [100 * max(0.0, r["success-rate"] - r["low"]) for r in mine]  # Wilson's bound at 0 of n: -1e-17
        above = [100 * max(0.0, r["high"] - r["success-rate"]) for r in mine]
        axis.errorbar(x, y, yerr=[below, above], marker="o", capsize=3, label=label)
    sizes = sorted({r["owners"] for r in rows})
    axis.set_xscale("log", base=2)
    axis.set_xticks(sizes, labels=[str(n) for n in sizes])
    axis.set(xlabel="owners in the federation", ylabel="success (%)", ylim=(0, 100),
             title="the same training, more owners: success with its 95% interval")  # fmt: skip
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")


def report(rows: list[dict], args: argparse.Namespace) -> None:
    print(f"\ngenerated sim-cube owners x {args.demos} demonstrations, {args.per_round} a round, {args.rounds} rounds "
          f"x {args.local_steps} steps, {args.model}, seeds {args.seeds}; {args.sim_episodes} episodes per seed and "
          "set-up:")  # fmt: skip
    print(f"{'owners':<7} {'model, where':<26} {'success (all seeds)':<26} McNemar p vs {min(args.sizes)} owners")
    for r in rows:
        low, high, n = 100 * r["low"], 100 * r["high"], r["episodes"]
        text = f"{100 * r['success-rate']:.0f}% [{low:.0f}, {high:.0f}] of {n}"
        print(f"{r['owners']:<7} {r['model']:<26} {text:<26} {r['mcnemar-p-vs-smallest']:.2g}")


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench owners", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=positive(int), nargs="+", default=[4, 16, 64], help="owners per federation")
    parser.add_argument("--per-round", type=positive(int), default=4, help="owners sampled each round, every size")
    add_sim_cube_recipe(parser, demos=10)
    parser.add_argument("--unseen", type=positive(int), default=4, help="owners in no run, whose set-ups judge")
    parser.add_argument("--personal-owners", type=positive(int), default=4, help="owners 0 to this - 1: personal")
    parser.add_argument("--output-dir", default="outputs/bench-owners")
    parser.add_argument("--json", default=None, help="write the figures here")
    return parser


def check(parser: OneSentenceParser, args: argparse.Namespace) -> None:
    """Settings that cannot make the comparison, refused in one sentence before anything is recorded."""
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds got {args.seeds}; expected different seeds")
    if len(set(args.sizes)) != len(args.sizes) or min(args.sizes) < max(args.per_round, args.personal_owners):
        parser.error(
            f"--sizes got {args.sizes}; expected different sizes, each at least --per-round ({args.per_round}) and "
            f"--personal-owners ({args.personal_owners}: they take part in every run)"
        )
    if args.demos <= RunConfig.eval_episodes:
        parser.error(f"--demos got {args.demos}; expected more than the {RunConfig.eval_episodes} each owner holds out")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    check(parser, args)
    out = Path(args.output_dir)
    largest = load_registry(str(owners_registry(out, max(args.sizes))))
    with native_output_to(out / "assets.log"):
        generate(largest, args.demos)  # every size's owners are the first of these
    unseen = [f"sim-so101-owner-{max(args.sizes) + k}-cube" for k in range(args.unseen)]
    started = time.perf_counter()
    rolled = {size: {seed: run_size(args, size, seed, unseen) for seed in args.seeds} for size in args.sizes}
    rows = table(rolled, unseen, args.personal_owners)
    report(rows, args)
    figures = {"settings": vars(args), "unseen": unseen, "rows": rows, "wall-s": time.perf_counter() - started,
               "rollouts": {str(n): {str(s): r for s, r in seeds.items()} for n, seeds in rolled.items()}}  # fmt: skip
    write_json(args.json, figures)
    chart(rows, out / "owners.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
