"""Robustness: does lerobot's image augmentation keep a policy working in rooms no owner has?

On the four hand-written sim-cube owners (configs/sim-cube-registry.toml, ``--demos`` recorded
once), once per ``--seeds`` training seed and once without and once with ``image-transforms``
(lerobot's ``ImageTransforms`` on every training frame, on the owner's machine), it trains

- the **global** model: the federation through the real app (``flwr run``, simulated clients,
  Nesterov, the documented sim-cube recipe);
- the **centralised** model: every owner's batches pooled, as many steps as the federation's owners
  take together (zk0.bench.models.centralised), augmented alike;
- each owner's **personal** model: the global model fine-tuned ``--personal-steps`` on the owner's
  own data, as ``personal-steps`` does (augmented alike);

and rolls each out on the same ``--sim-episodes`` seeded episodes: the global and centralised
models in the server's span and in each ``--conditions`` outside it (zk0.sim.tasks: the server's
set-up with one axis of its look drawn beyond every owner's), each personal model in its owner's
own set-up and in it with the lighting moved outside the span (``--owner-conditions``). Each rate
has its 95% interval over every seed's episodes, its ratio to the same model's rate in its span
(the server's, or the owner's own), and McNemar's test of with against without transforms over
the same episodes. Every trained model and finished rollout is kept in ``--output-dir``
(zk0.bench.stash), so the same command continues a stopped run, and seeds run as separate
commands can be tabled together by one more with all of them.

    python -m zk0.bench robustness [--seeds 42 43] [--demos 30] [--rounds 20] [--local-steps 75]
        [--model tiny-128] [--lr 1e-3] [--personal-steps 300] [--sim-episodes 100] [--episode-length 300]
        [--conditions dim-0 bright-0 tint-0 camera-0 table-0] [--owner-conditions dim-0 bright-0]
        [--output-dir outputs/bench-robustness] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from zk0.artifacts.logs import native_output_to
from zk0.bench.client import write_json
from zk0.bench.models import (
    JUDGED_BY_ROLLOUTS,
    SERVER,
    Weights,
    add_sim_cube_recipe,
    centralised,
    closed_loop_all,
    evaluation_sets,
    fine_tuned,
    generate,
    kept_federation,
)
from zk0.bench.stash import Stash
from zk0.common.errors import OneSentenceParser, positive
from zk0.config import RunConfig
from zk0.data.registry import PROJECT_ROOT, load_registry
from zk0.federation.client import ClientSession, build_client
from zk0.learning.policy import snapshot
from zk0.learning.rates import mcnemar, rate_text, wilson
from zk0.sim.tasks import OUTSIDE

REGISTRY = PROJECT_ROOT / "configs" / "sim-cube-registry.toml"
TRANSFORMS = {"off": False, "on": True}
LIGHTING = ("dim", "bright", "tint")  # the conditions the lighting target covers
SETTINGS = ("demos", "rounds", "local_steps", "batch_size", "model", "lr", "personal_steps", "clients", "wire_dtype")


def condition(name: str, base: str) -> str:
    """The simulator's name of condition ``name`` (``dim-0``) made from ``base`` (``sim-so101-eval-cube``:
    the server's set-up; ``sim-so101-left-cube``: an owner's)."""
    prefix = base.removesuffix("-cube").removesuffix("-eval")
    return f"{prefix}-outside-{name}-cube"


def training_run(args: argparse.Namespace, seed: int, transforms: bool) -> RunConfig:
    """The in-process models' run config: the federation's own keys."""
    return RunConfig(
        seed=seed,
        registry=str(REGISTRY),
        server_eval_dataset=load_registry(str(REGISTRY)).server.name,
        num_server_rounds=args.rounds,
        local_steps=args.local_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        model=args.model,
        min_train_clients=args.clients,
        personal_steps=args.personal_steps,
        image_transforms=transforms,
    )


def global_model(args: argparse.Namespace, run: RunConfig, stash: Stash, server_bundle) -> Weights:
    """The federation's final global model, trained through ``flwr run`` (kept in ``stash``)."""
    keys = {"registry": run.registry, "server-eval-dataset": run.server_eval_dataset, "model": run.model,
            "seed": run.seed, "eval-frequency": run.num_server_rounds, "proximal-mu": 0.0,
            "server-optimiser": "nesterov", "image-transforms": run.image_transforms, **JUDGED_BY_ROLLOUTS}  # fmt: skip
    return kept_federation(args, stash, args.clients, keys, server_bundle)


def train_models(args: argparse.Namespace, sessions: list[ClientSession], run: RunConfig, stash: Stash, columns: dict,
                 say) -> dict[str, Weights]:  # fmt: skip
    """The global, centralised and personal models of one seed with or without transforms."""
    start = snapshot(sessions[0].bundle)
    models = {"global": global_model(args, run, stash, columns[SERVER][0])}
    say("global model trained")
    cameras = load_registry(run.registry).model_cameras()
    models["centralised"] = stash.weights("centralised", lambda: centralised(sessions, run, start, cameras)[0])
    say("centralised model trained")
    for s in sessions:
        models[f"personal {s.index}"] = stash.weights(
            f"personal {s.index}", lambda s=s: fine_tuned(s, run, models["global"])
        )
    say("personal models trained")
    return models


def rollout_columns(args: argparse.Namespace, sessions: list[ClientSession], server: str) -> tuple[dict, dict]:
    """Which models are rolled out where (column -> models), and each added column's (processors, conditions)."""
    plan = {SERVER: ["global", "centralised"]}
    where = {}
    for name in args.conditions:
        plan[name] = ["global", "centralised"]
        where[name] = (SERVER, condition(name, server))
    for s in sessions:
        own = f"client {s.index}"
        plan[own] = [f"personal {s.index}"]
        for name in args.owner_conditions:
            plan[f"{own} {name}"] = [f"personal {s.index}"]
            where[f"{own} {name}"] = (own, condition(name, s.split.entry.name))
    return plan, where


def run_seed(args: argparse.Namespace, seed: int) -> dict[str, dict]:
    """Every model of training seed ``seed``, without and with transforms, rolled out:
    {transforms: {model: {column: rates}}}."""
    registry = load_registry(str(REGISTRY))
    started = time.perf_counter()
    rolled = {}
    for label, transforms in TRANSFORMS.items():
        run = training_run(args, seed, transforms)
        folder = Path(args.output_dir) / f"seed-{seed}" / f"transforms-{label}"
        stash = Stash(folder, {k: vars(args)[k] for k in SETTINGS})

        def say(line: str, label: str = label) -> None:
            print(f"  seed {seed}, transforms {label}: {line} ({time.perf_counter() - started:.0f} s)", flush=True)

        cameras = registry.model_cameras()
        sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients[: args.clients])]
        columns = evaluation_sets(sessions, registry, run)
        models = train_models(args, sessions, run, stash, columns, say)
        plan, where = rollout_columns(args, sessions, run.server_eval_dataset)
        rolled[label] = closed_loop_all(
            plan, models, columns, args.sim_episodes, RunConfig.seed, say, stash, where, args.episode_length
        )
    return rolled


def span_of(column: str) -> str:
    """The column a model's rate in ``column`` is compared with: its own span, the owner's own set-up
    (``client 0`` for ``client 0 dim-0``) or the server's (for the conditions made from it)."""
    return " ".join(column.split()[:2]) if column.startswith("client ") else SERVER


def table(seeds: dict[int, dict], args: argparse.Namespace) -> list[dict]:
    """One row per model, transforms setting and column: its rate over every seed's episodes, its
    interval, its ratio to its span's rate, and McNemar's p for with against without transforms."""

    def outcomes(label: str, model: str, column: str) -> list[int]:
        return [o for seed in sorted(seeds) for o in seeds[seed][label][model][column]["outcomes"]]

    rows = []
    first = seeds[min(seeds)]["off"]
    for model, columns in first.items():
        for column in columns:
            for label in TRANSFORMS:
                got = outcomes(label, model, column)
                span = outcomes(label, model, span_of(column))
                rate, base = sum(got) / len(got), sum(span) / len(span)
                low, high = wilson(sum(got), len(got))
                rows.append({
                    "model": model, "column": column, "transforms": label, "success-rate": rate, "low": low,
                    "high": high, "episodes": len(got), "vs-span": rate / base if base else None,
                    "per-seed": [seeds[s][label][model][column]["success-rate"] for s in sorted(seeds)],
                    "mcnemar-p-on-vs-off": mcnemar(outcomes("on", model, column), outcomes("off", model, column)),
                })  # fmt: skip
    return rows


def targets(rows: list[dict]) -> dict[str, bool]:
    """The issue's targets: with transforms, >= 0.8x the span's rate in every lighting condition
    (the global model; each personal model in its own lighting conditions), and in the server's span
    the global model within the noise of its rate without (McNemar p >= 0.05)."""
    on = [r for r in rows if r["transforms"] == "on"]
    lit = [r for r in on if any(r["column"].split()[-1].startswith(axis) for axis in LIGHTING)]
    span = next(r for r in on if r["model"] == "global" and r["column"] == SERVER)
    return {
        "global >= 0.8x in lighting": all((r["vs-span"] or 0) >= 0.8 for r in lit if r["model"] == "global"),
        "personal >= 0.8x in own lighting": all((r["vs-span"] or 0) >= 0.8 for r in lit if r["model"] != "global"
                                                and r["model"] != "centralised"),  # fmt: skip
        "global in span within noise": span["mcnemar-p-on-vs-off"] >= 0.05,
    }


def report(rows: list[dict], met: dict[str, bool], args: argparse.Namespace, seeds: list[int]) -> None:
    print(
        f"\nsim-cube owners: {args.clients} x {args.demos} demonstrations, {args.rounds} rounds x {args.local_steps} "
        f"steps, {args.model}, seeds {seeds}; success on {args.sim_episodes} seeded episodes per seed and condition:"
    )
    print(f"{'model':<12} {'conditions':<20} {'transforms':<10} {'success (all seeds)':<24} {'per seed':<12} "
          f"{'/ span':<7} {'on vs off p'}")  # fmt: skip
    for r in rows:
        ratio = "-" if r["vs-span"] is None else f"{r['vs-span']:.2f}x"
        per_seed = ", ".join(f"{100 * x:.0f}%" for x in r["per-seed"])
        p = f"{r['mcnemar-p-on-vs-off']:.2g}" if r["transforms"] == "on" else ""
        text = rate_text(r["success-rate"], r["episodes"])
        print(f"{r['model']:<12} {r['column']:<20} {r['transforms']:<10} {text:<24} {per_seed:<12} {ratio:<7} {p}")
    for name, ok in met.items():
        print(f"target {name}: {'met' if ok else 'missed'}")


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench robustness", description=__doc__.split("\n\n")[0])
    axes = [f"{axis}-{i}" for axis in OUTSIDE for i in range(10)]
    add_sim_cube_recipe(parser, demos=30)
    parser.add_argument("--clients", type=positive(int), default=4, help="the first this many owners of the registry")
    parser.add_argument("--conditions", nargs="+", choices=axes, default=[f"{axis}-0" for axis in OUTSIDE],
                        help="conditions outside the span, made from the server's set-up")  # fmt: skip
    parser.add_argument(
        "--owner-conditions", nargs="*", choices=axes, default=["dim-0", "bright-0"],
        help="conditions outside the span made from each owner's own set-up (personal models)",
    )  # fmt: skip
    parser.add_argument("--output-dir", default="outputs/bench-robustness")
    parser.add_argument("--json", default=None, help="write the figures here")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds got {args.seeds}; expected different seeds")
    registry = load_registry(str(REGISTRY))
    if args.clients > len(registry.clients):
        parser.error(f"--clients got {args.clients}; {REGISTRY.name} has {len(registry.clients)} owners")
    if args.demos <= RunConfig.eval_episodes:
        held_out = RunConfig.eval_episodes
        parser.error(f"--demos got {args.demos}; expected more than the {held_out} each owner holds out")
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    with native_output_to(out / "assets.log"):
        generate(registry, args.demos)
    started = time.perf_counter()
    seeds = {seed: run_seed(args, seed) for seed in args.seeds}
    rows = table(seeds, args)
    met = targets(rows)
    report(rows, met, args, args.seeds)
    figures = {"settings": vars(args), "rows": rows, "targets": met, "wall-s": time.perf_counter() - started,
               "seeds": {str(s): r for s, r in seeds.items()}}  # fmt: skip
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
