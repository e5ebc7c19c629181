"""Privacy: what differential privacy and robust aggregation cost in closed loop, and what one hostile owner does.

On ``--owners`` simulated SO-101 owners generated from one ``[tool.zk0.owners]`` table (``kind =
"sim-cube"``), or on ``--registry``'s client sets, ``--demos`` demonstrations each (recorded once),
every run through the real app (``flwr run``, simulated clients), once per ``--seeds`` training seed:

- **non-private**: ``dp = "off"``, the weighted mean;
- **record e=E** for each ``--epsilons`` E: ``dp = "record"``, each owner's DP-SGD noise calibrated
  by Opacus so that the run spends E (at ``--delta``) of each owner's demonstrations; with
  ``--recipes NAME:KEYS ...``, **record e=E NAME** for each recipe instead, its run-config keys
  (``dp-batch``, ``dp-frames``, ``dp-train``, ``local-steps``, ``lr``, ...) over the run's (a
  recipe that sets its own ``dp-epsilon-budget`` or ``dp-noise-multiplier`` runs once, as
  **record NAME**: a noiseless ceiling, or the noise of more demonstrations);
- **owner e=E**: ``dp = "owner"``, Flower's central DP calibrated by dp-accounting so that the
  run's rounds spend E, each update clipped to the median update norm the non-private run's
  first round measured (the usual choice: about half the updates are clipped);
- for each ``--aggregations`` rule A (Flower's or ByzFL's; ``nnm+meamed`` is ByzFL's NNM
  pre-aggregator then its Meamed), each ``--attacks`` attack K and each ``--hostile`` count H,
  **A, K xH**: the last H owners are hostile. ``negated``: each sends its trained update negated
  and scaled by ``--hostile-factor`` (2.9: under ``update-clip = 3`` times the others' median, so
  the clip passes it); the others are ByzFL's attacks of the honest updates, which only an
  attacker who sees them all could send, substituted at the server (zk0.bench.attacks). And **A**
  without them (the rule's cost when nobody attacks, its ``hostile-owners`` the largest H;
  ``mean`` without them is the non-private run).

With ``--public N --pretrain-steps S`` (issue 63's question), the registry has N public set-ups
of the server's own, a policy is pretrained on them for S steps once (``zk0 pretrain``, kept in
the output folder), every run starts from it, and **public base alone** is rolled out beside them:
what DP keeps of the owners' gain over the base. ``--aggregations monna`` (the trusted direction)
needs the public sets too.

Every final model is rolled out on the same ``--sim-episodes`` seeded episodes in the server's
span of conditions: success with its 95% interval, and McNemar's test against the same seed's
non-private model. Tables give the mean over seeds and the interval over every seed's episodes.
Prints the tables and writes JSON (``--json``).

    python -m zk0.bench privacy [--owners 16 | --registry configs/sim-cube-registry.toml] [--demos 10]
        [--public 4 --public-demos 10 --pretrain-steps 1500] [--rounds 20] [--local-steps 75]
        [--model tiny-128] [--lr 1e-3] [--epsilons 8 2] [--recipes NAME:KEYS ...] [--delta 1e-5] [--seeds 42 43]
        [--aggregations mean median trimmed-mean krum multi-krum nnm+meamed ...] [--attacks negated alie ...]
        [--hostile 1 3] [--hostile-factor -2.9]
        [--sim-episodes 100] [--output-dir outputs/bench-privacy] [--json FILE] [--seeds-from JSON]

``--seeds-from`` adds the seeds of an earlier run of the same settings (its JSON) to the tables,
so seeds can be trained one invocation at a time.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch
from flwr.common.config import parse_config_args

from zk0.artifacts.logs import native_output_to
from zk0.artifacts.resume import checkpoint_trainable
from zk0.artifacts.run_folder import checkpoints
from zk0.bench.attacks import ATTACKS, attacked_app
from zk0.bench.client import write_json
from zk0.bench.models import SERVER, closed_loop_all, generate
from zk0.common.errors import OneSentenceParser, Zk0Error, positive
from zk0.config import AGGREGATIONS, BYZFL_RULES, OFFLINE_MODELS, PRE_AGGREGATIONS, RunConfig, from_run_config
from zk0.data.loaders import open_evaluation, open_metadata
from zk0.data.registry import PROJECT_ROOT, load_registry
from zk0.deployment.simulation import run_federation
from zk0.federation.client import build_client
from zk0.federation.pretraining import pretrain
from zk0.federation.privacy import calibrated_noise
from zk0.learning.policy import build_policy, snapshot
from zk0.learning.rates import mcnemar, rate_text, wilson

NON_PRIVATE = "non-private"
PUBLIC_BASE = "public base alone"
NOISELESS = {"dp-epsilon-budget": 1e30, "dp-noise-multiplier": 1e-12}  # clipping and draws alone


def owners_registry(folder: Path, owners: int, public: int = 0) -> Path:
    """A registry of ``owners`` generated sim-cube owners, ``public`` public set-ups and their server set."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "owners-registry.toml"
    path.write_text(f'[tool.zk0.owners]\ncount = {owners}\nkind = "sim-cube"\npublic = {public}\n')
    return path


def base_folder(args, out: Path) -> Path:
    """Where the public base of ``--model`` pretrained ``--pretrain-steps`` steps is kept."""
    return out / f"public-base-{args.model}-{args.pretrain_steps}-steps"


def public_base(args, registry: Path, out: Path) -> Path | None:
    """With ``--pretrain-steps``: the policy pretrained on the registry's public sets (zk0 pretrain),
    made once and kept in the benchmark's folder; every run starts from it. None without."""
    if not args.pretrain_steps:
        return None
    base = base_folder(args, out)
    if not base.exists():
        run = from_run_config({"registry": str(registry), "model": args.model, "lr": args.lr})
        done = pretrain(run, args.pretrain_steps, base)
        print(
            f"  public base: {args.pretrain_steps} steps on {done['public-sets']} in {done['wall-s']:.0f} s", flush=True
        )
    return base


def owner_registry(parser: OneSentenceParser, path: Path):
    """``--registry``'s registry, refused in one sentence if it cannot be read."""
    try:
        return load_registry(str(path))
    except (OSError, Zk0Error) as err:
        parser.error(f"--registry: {str(err).rstrip('.')}")


# --aggregations: a rule, or ByzFL's pre-aggregator and a rule after it ("nnm+meamed")
RULES = (*AGGREGATIONS, *(f"{pre}+{rule}" for pre in PRE_AGGREGATIONS[1:] for rule in ("mean", *BYZFL_RULES)))


def recipes(args) -> dict[str, dict]:
    """``--recipes``' record-level recipes, name -> the run-config keys it changes (``{"": {}}``:
    the defaults alone)."""
    found = {}
    for recipe in args.recipes or [":"]:
        name, _, keys = recipe.partition(":")
        found[name] = parse_config_args([keys]) if keys.strip() else {}
    return found


def own_noise(keys: dict) -> bool:
    """Whether a recipe sets its own noise or budget (a noiseless ceiling, the noise of more
    demonstrations): it runs once, whatever ``--epsilons`` says, and has no noise crossover."""
    return bool({"dp-epsilon-budget", "dp-noise-multiplier"} & set(keys))


def rule_keys(rule: str, hostile: int) -> dict:
    """The run-config keys of ``--aggregations``' ``rule`` outvoting ``hostile`` owners."""
    pre, _, name = rule.rpartition("+")
    return {"aggregation": name, **({"pre-aggregation": pre} if pre else {}), "hostile-owners": hostile}


def planned_runs(args, owner_clip: float | None) -> dict[str, dict]:
    """label -> the run-config keys it adds, and its attack (name, hostile owners) or None."""
    runs: dict[str, dict] = {NON_PRIVATE: {"keys": {}, "attack": None}}
    for epsilon in args.epsilons:
        privacy = {"dp-epsilon-budget": epsilon, "dp-delta": args.delta}
        for name, keys in recipes(args).items():
            if own_noise(keys) and epsilon != args.epsilons[0]:
                continue
            label = f"record {name}" if own_noise(keys) else f"record e={epsilon:g}" + (f" {name}" if name else "")
            runs[label] = {"keys": {"dp": "record", **privacy, **keys}, "attack": None}
        if owner_clip is not None:
            runs[f"owner e={epsilon:g}"] = {"keys": {"dp": "owner", "dp-clip": owner_clip, **privacy}, "attack": None}
    for rule in args.aggregations:
        if rule != "mean":
            runs[rule] = {"keys": rule_keys(rule, max(args.hostile)), "attack": None}
        for attack in args.attacks:
            for hostile in args.hostile:
                runs[f"{rule}, {attack} x{hostile}"] = {"keys": rule_keys(rule, hostile), "attack": (attack, hostile)}
    return runs


def starting_model(args) -> str:
    """What every run starts from: the public base (``args.start``, set by ``main``), else ``--model``."""
    return str(args.start) if args.start else args.model


def run_config(args, registry: Path, seed: int, keys: dict) -> str:
    settings = {
        "registry": str(registry),
        "server-eval-dataset": load_registry(str(registry)).server.name,
        "model": starting_model(args),
        "num-server-rounds": args.rounds,
        "local-steps": args.local_steps,
        "lr": args.lr,
        "seed": seed,
        "checkpoint-interval": args.rounds,
        "min-train-clients": args.owners - 1,  # a round goes on without one owner that fails
        "eval-batches": 1,
        **keys,
    }
    return " ".join(f"{k}={json.dumps(v)}" if isinstance(v, str) else f"{k}={v}" for k, v in settings.items())


def median_update_norm(history: dict) -> float:
    """The median of the owners' update norms in round 1 (what owner-level DP clips to)."""
    clients = history["rounds"][1]["clients"].values()
    return statistics.median(c["train"]["update-norm"] for c in clients if "update-norm" in c.get("train", {}))


def rollouts(args, registry_path: Path, finals: dict[str, Path]) -> dict[str, dict]:
    """Every run's final model on the same seeded episodes in the server's conditions."""
    registry = load_registry(str(registry_path))
    run = RunConfig(registry=str(registry_path), server_eval_dataset=registry.server.name, model=args.model)
    entry = registry.get(run.server_eval_dataset)
    meta = open_metadata(entry)
    bundle = build_policy(run, meta, entry, registry.model_cameras())
    split = open_evaluation(entry, meta, bundle.policy.config, run)
    models = {name: checkpoint_trainable(path, bundle).to_torch_state_dict() for name, path in finals.items()}
    rolled = closed_loop_all({SERVER: list(models)}, models, {SERVER: (bundle, split, None)}, args.sim_episodes,
                             run.seed, lambda line: print(f"  {line}", flush=True))  # fmt: skip
    return {name: row[SERVER] for name, row in rolled.items()}


def noise_crossover(args, registry_path: Path, epsilon: float, recipe: dict | None = None) -> dict:
    """How many owners owner-level DP needs before the noise on the released average is no larger
    than record-level DP's, both spending ``epsilon`` over the run.

    Record-level: owner 0's first round trained twice from the same start with the same draws and
    clipping, once with the calibrated noise and once with none (noise 1e-12, no budget); the noise's
    share of the update is the difference's norm over the noiseless update's. Averaged over N
    owners, independent noises shrink as 1/sqrt(N). Owner-level: noise of std z * clip on each of
    the d weights of the sum, divided by N. Taken at its most favourable (every update at the clip
    and pointing one way), its share is z * sqrt(d) / N, which falls to record-level's at
    N = (z * sqrt(d) / share)^2. With ``recipe`` (a ``--recipes`` item's keys), that recipe's noise.

    AdamW steps each weight by about the learning rate whatever the size of its gradient, so once
    the noise dominates, the noisy update stops growing with it: the share then reads alike at
    epsilon 8 and 2 (measured: 154% and 154%). The cosine between the noisy and the noiseless
    update says how much of it still points the noiseless way."""
    registry = load_registry(str(registry_path))
    keys = {"registry": str(registry_path), "server-eval-dataset": registry.server.name,
            "model": starting_model(args),
            "num-server-rounds": args.rounds, "local-steps": args.local_steps, "lr": args.lr, "dp": "record",
            "dp-delta": args.delta, **(recipe or {})}  # fmt: skip
    updates, noise, rate = {}, 0.0, 0.0
    for label, extra in (("noisy", {"dp-epsilon-budget": epsilon}), ("clean", NOISELESS)):
        run = from_run_config({**keys, **extra})
        session = build_client(run, registry.clients[0], registry.model_cameras())
        start = snapshot(session.bundle)
        session.trainer.fit(run.local_steps, 0.0, global_step=0)
        end = snapshot(session.bundle)
        updates[label] = torch.cat([(end[name] - start[name]).flatten() for name in start])
        noise, rate = noise or session.trainer.noise_multiplier, session.trainer.sample_rate
    record_share = float((updates["noisy"] - updates["clean"]).norm() / updates["clean"].norm())
    cosine = float(torch.nn.functional.cosine_similarity(updates["noisy"], updates["clean"], dim=0))
    owner_noise = calibrated_noise(epsilon, args.delta, args.rounds)
    owner_share_one = owner_noise * math.sqrt(updates["clean"].numel())
    return {
        "record-noise-multiplier": noise,
        "sample-rate": rate,
        "record-noise-share": record_share,
        "record-update-cosine": cosine,  # how much of the noisy update points where the noiseless one does
        "owner-noise-multiplier": owner_noise,
        "weights": updates["clean"].numel(),
        "owner-noise-share-one-owner": owner_share_one,
        "owners-to-match": math.ceil((owner_share_one / record_share) ** 2),
    }


def check_recipes(args, parser: OneSentenceParser, out: Path) -> None:
    """Each ``--recipes`` item named once, its keys read and valid under ``dp = "record"`` for the
    model the runs start from (the public base, if any), before any run."""
    start = str(base_folder(args, out)) if args.pretrain_steps else args.model
    seen = set()
    for recipe in args.recipes:
        name = recipe.partition(":")[0]
        if ":" not in recipe or not name or name in seen:
            parser.error(
                f"--recipes got {recipe!r}; expected NAME:KEYS with a name of its own, such as 'full:dp-batch=0'"
            )
        seen.add(name)
        try:
            from_run_config({"dp": "record", "model": start, **parse_config_args([recipe.partition(":")[2]])})
        except Exception as err:  # flwr's parse errors, zk0's ConfigError: one sentence either way
            parser.error(f"--recipes {name}: {str(getattr(err, 'message', err)).rstrip('.')}")


def summary(success: dict[str, dict], seeds: list[int], labels: list[str]) -> dict[str, dict]:
    """For each run: its mean rate over seeds, the interval over every seed's episodes, its ratio
    to the non-private run's, and McNemar's test against it over every seed's paired episodes."""
    table = {}
    base = [o for seed in seeds for o in success[f"{NON_PRIVATE} seed {seed}"]["outcomes"]]
    for label in labels:
        outcomes = [o for seed in seeds for o in success[f"{label} seed {seed}"]["outcomes"]]
        low, high = wilson(sum(outcomes), len(outcomes))
        rate = sum(outcomes) / len(outcomes)
        table[label] = {
            "success-rate": rate,
            "low": low,
            "high": high,
            "episodes": len(outcomes),
            "per-seed": [success[f"{label} seed {seed}"]["success-rate"] for seed in seeds],
            "vs-non-private": rate / (sum(base) / len(base)) if sum(base) else None,
            "mcnemar-p": mcnemar(outcomes, base),
        }
    return table


SAME = ("owners", "registry", "demos", "rounds", "local_steps", "model", "lr", "epsilons", "recipes", "delta", "no_owner_level",
        "aggregations", "attacks", "hostile", "hostile_factor", "sim_episodes", "public", "public_demos",
        "pretrain_steps")  # fmt: skip


def earlier_seeds(args, parser: OneSentenceParser) -> dict:
    """``--seeds-from``'s figures, refused in one sentence when trained with other settings or seeds."""
    earlier = json.loads(Path(args.seeds_from).read_text())
    for key in SAME:
        if earlier["settings"][key] != getattr(args, key):
            parser.error(
                f"--seeds-from {args.seeds_from} was run with --{key.replace('_', '-')} "
                f"{earlier['settings'][key]}, this run with {getattr(args, key)}; expected the same settings"
            )
    if set(earlier["settings"]["seeds"]) & set(args.seeds):
        parser.error(
            f"--seeds-from {args.seeds_from} has seeds {earlier['settings']['seeds']} already; expected others"
        )
    return earlier


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench privacy", description=__doc__.split("\n\n")[0])
    parser.add_argument("--owners", type=positive(int), default=16, help="generated sim-cube owners")
    parser.add_argument(
        "--registry",
        default=None,
        help="a registry whose client sets are the owners instead (configs/sim-cube-registry.toml: the study's four "
        "hand-written set-ups); --owners is then its number of clients",
    )
    parser.add_argument("--demos", type=positive(int), default=10, help="demonstrations per owner")
    parser.add_argument("--public", type=int, default=0, help="generated public set-ups (with --owners)")
    parser.add_argument("--public-demos", type=positive(int), default=10, help="demonstrations per public set")
    parser.add_argument(
        "--pretrain-steps", type=int, default=0, help="pretrain on the public sets first; every run starts from it"
    )
    parser.add_argument("--rounds", type=positive(int), default=20)
    parser.add_argument("--local-steps", type=positive(int), default=75)
    parser.add_argument("--model", choices=OFFLINE_MODELS, default="tiny-128")
    parser.add_argument("--lr", type=positive(float), default=1e-3)
    parser.add_argument("--epsilons", type=positive(float), nargs="*", default=[8.0, 2.0])
    parser.add_argument(
        "--recipes",
        nargs="*",
        default=[],
        help='record-level recipes to compare, each NAME:KEYS (run-config keys, e.g. "full:dp-batch=0 local-steps=3")',
    )
    parser.add_argument("--delta", type=positive(float), default=1e-5)
    parser.add_argument("--no-owner-level", action="store_true", help="skip the owner-level DP runs")
    parser.add_argument("--seeds", type=int, nargs="+", default=[42, 43])
    parser.add_argument(
        "--aggregations", nargs="*", choices=RULES, default=["mean", "median", "trimmed-mean", "krum", "multi-krum"]
    )
    parser.add_argument(
        "--attacks", nargs="*", choices=ATTACKS, default=["negated"], help="zk0.bench.attacks; none: no hostile runs"
    )
    parser.add_argument("--hostile", type=positive(int), nargs="+", default=[1], help="hostile owners, the last ones")
    parser.add_argument("--hostile-factor", type=float, default=-2.9, help="negated: the hostile update's factor")
    parser.add_argument("--sim-episodes", type=positive(int), default=100)
    parser.add_argument("--output-dir", default="outputs/bench-privacy")
    parser.add_argument("--json", default=None, help="write the figures here")
    parser.add_argument(
        "--seeds-from",
        default=None,
        help="a JSON this benchmark wrote with the same settings: its seeds join the table",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.demos <= RunConfig.eval_episodes:
        parser.error(
            f"--demos got {args.demos}; expected more than the {RunConfig.eval_episodes} each owner holds out (eval-episodes)"
        )
    if len(set(args.seeds)) != len(args.seeds):
        parser.error(f"--seeds got {args.seeds}; expected different seeds")
    for flag, value in (("--public", args.public), ("--pretrain-steps", args.pretrain_steps)):
        if value < 0:
            parser.error(f"{flag} got {value}; expected 0 (none) or more")
    out = Path(args.output_dir).resolve()
    check_recipes(args, parser, out)
    if args.registry:
        registry = Path(args.registry).resolve()
        args.owners = len(owner_registry(parser, registry).clients)
    else:
        registry = owners_registry(out, args.owners, args.public)
    if not load_registry(str(registry)).public and (args.pretrain_steps or "monna" in args.aggregations):
        parser.error(
            "--pretrain-steps and --aggregations monna need public sets; expected --public N (or a --registry with "
            'role = "public" entries)'
        )
    if args.owners < 2 * max(args.hostile) + 2:
        parser.error(
            f"--owners got {args.owners}; expected {2 * max(args.hostile) + 2} or more (--hostile "
            f"{max(args.hostile)} owners, more than twice as many to outvote them, and one a round may miss)"
        )
    with native_output_to(out / "assets.log"):
        generate(load_registry(str(registry)), args.demos, args.public_demos)
    apps = {
        (attack, hostile): attacked_app(
            out / f"attacked-app-{attack}-x{hostile}",
            attack,
            range(args.owners - hostile, args.owners),
            args.hostile_factor,
        )
        for attack in args.attacks
        for hostile in args.hostile
    }
    started = time.perf_counter()
    args.start = public_base(args, registry, out)
    figures: dict = {"settings": {k: v for k, v in vars(args).items() if k != "start"}, "runs": {}}
    finals: dict[str, Path] = {}

    def train(label: str, seed: int, plan: dict) -> dict | None:
        name = f"{label} seed {seed}"
        app = apps[plan["attack"]] if plan["attack"] else PROJECT_ROOT
        config = run_config(args, registry, seed, plan["keys"])
        history = run_federation(config, args.owners, out / name.replace(" ", "-"), name, app)
        if history is not None:
            figures["runs"][name] = {"wall-s": history["rounds"][-1]["wall-s"], "config": plan["keys"]}
            finals[name] = checkpoints(Path(history["run-dir"]))[-1][1]
            print(f"  {name}: trained in {figures['runs'][name]['wall-s']:.0f} s", flush=True)
        return history

    for seed in args.seeds:
        first = train(NON_PRIVATE, seed, planned_runs(args, None)[NON_PRIVATE])
        if first is None:
            return 1
        clip = median_update_norm(first)
        figures["runs"][f"{NON_PRIVATE} seed {seed}"]["median-update-norm"] = clip
        plan = planned_runs(args, None if args.no_owner_level else clip)
        labels = list(plan) + ([PUBLIC_BASE] if args.start else [])
        if args.start:  # the starting point alone: what the owners add is the runs' gain over it
            finals[f"{PUBLIC_BASE} seed {seed}"] = args.start
        for label, spec in list(plan.items())[1:]:
            if train(label, seed, spec) is None:
                return 1
    figures["training-wall-s"] = time.perf_counter() - started
    figures["noise-crossover"] = {
        f"e={e:g}" + (f" {name}" if name else ""): noise_crossover(args, registry, e, keys)
        for e in args.epsilons
        for name, keys in recipes(args).items()
        if not own_noise(keys)
    }
    figures["success"] = rollouts(args, registry, finals)
    seeds = list(args.seeds)
    if args.seeds_from:
        earlier = earlier_seeds(args, parser)
        figures["success"] |= earlier["success"]
        figures["runs"] |= earlier["runs"]
        seeds = earlier["settings"]["seeds"] + seeds
    figures["table"] = summary(figures["success"], seeds, labels)
    figures["owner-noise"] = {
        f"e={e:g}": calibrated_noise(e, args.delta, args.rounds) for e in args.epsilons
    }  # the noise multiplier on each round's sum: its std on the average is this x clip / owners
    figures["wall-s"] = time.perf_counter() - started
    report(figures, args)
    write_json(args.json, figures)
    return 0


def report(figures: dict, args) -> None:
    owners = f"{args.owners} sim-cube owners" + (f" ({args.registry})" if args.registry else "")
    print(
        f"\n{owners} x {args.demos} demonstrations, {args.rounds} rounds x {args.local_steps} "
        f"steps, {args.model}; success on {args.sim_episodes} seeded episodes per seed in the server's span, seeds "
        f"{args.seeds}:"
    )
    print(f"{'run':<26} {'success (all seeds)':<26} {'per seed':<18} {'/ non-private':<14} McNemar p")
    for label, row in figures["table"].items():
        ratio = "-" if row["vs-non-private"] is None else f"{row['vs-non-private']:.2f}x"
        seeds = ", ".join(f"{100 * r:.0f}%" for r in row["per-seed"])
        text = rate_text(row["success-rate"], row["episodes"])
        print(f"{label:<26} {text:<26} {seeds:<18} {ratio:<14} {row['mcnemar-p']:.2g}")
    for label, c in figures["noise-crossover"].items():
        print(
            f"{label}: record-level noise is {100 * c['record-noise-share']:.0f}% of one owner's update, which keeps "
            f"a cosine of {c['record-update-cosine']:.2f} with the noiseless one (noise multiplier "
            f"{c['record-noise-multiplier']:.3g}); owner-level (noise multiplier "
            f"{c['owner-noise-multiplier']:.3g} over {c['weights']:,} weights) matches it from "
            f"{c['owners-to-match']:,} owners"
        )
    print(f"wall time: {figures['wall-s'] / 60:.0f} min ({figures['training-wall-s'] / 60:.0f} training)")


if __name__ == "__main__":
    sys.exit(main())
