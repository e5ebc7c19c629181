"""Study: does federating help? The federation against centralised and local-only training.

On the same synthetic clients, model, batch size and number of samples, with one learning rate
(``--lr``; ``--federation-lr`` gives the federation another), it trains

- the federation through the real app (``flwr run``, simulated clients), once per
  ``--federations`` entry: FedProx (plain averaging with ``--proximal-mu``), and with
  ``proximal-mu = 0`` FedAvg and each server optimiser (FedAvgM, Nesterov, FedAdam, FedYogi:
  zk0.federation.server_optimisers, at their defaults or ``--server-lr``/``--server-momentum``);
- **centralised**: one policy and one optimizer on every client's training episodes pooled,
  taking batches from each client's own loader in turn, each preprocessed with that client's
  own processors (camera mapping, normalisation), for as many steps as all clients take in the
  federation together (zk0.learning.training.PooledTrainer);
- **equal steps**: the same pooled training for only the federation's sequential steps (rounds x
  local steps), each on a batch from every client together (batch = clients x batch): the same
  samples again, so it splits "fewer sequential steps" from "federating";
- **local-only**: each client alone, for the steps it takes in the federation;

- with ``--personal-steps N``, **personal** *i*: the first federation's model fine-tuned N steps on
  client *i*'s own data as a federation's client fine-tunes its personal model (zk0.federation.personal, a
  quarter of ``--lr``), and each local-only model fine-tuned alike, so the two have seen as many
  samples; the paired comparisons in each owner's own conditions then answer "what does joining
  give my robot";

- with ``--new-owner NAME``, an owner who joins once the federation is trained, with only
  ``--new-demos`` demonstrations (a simulated set-up, e.g. of a task no owner teaches): the first
  federation's model fine-tuned ``--new-steps`` steps on them at a quarter of ``--lr``, against a
  model trained the same steps on them from the start at ``--lr``, both rolled out in the new
  owner's conditions beside the global model itself;

then evaluates every model, and the common starting model, on every client's held-out
episodes and on the server's evaluation set (action MSE in joint units, and the policy loss),
exactly as the federation's clients and server evaluate. It does so in two settings:
``mild``, the default synthetic clients, and ``noniid``, where each client sees targets only in
its own quarter of the table and its arm approaches them at its own rate
(configs/noniid-registry.toml). Prints the matrices and writes JSON and a PNG chart.

The ``sim`` setting trains on the simulated SO-101 owners' demonstrations (configs/sim-registry.toml,
``--demos`` per client) and also rolls every model out in the simulator (``--sim-episodes`` seeded
episodes) in the server's span of conditions and in each client's own: success, not only MSE.
``sim-cube`` is the same with the target cube's xy in every state (configs/sim-cube-registry.toml): a
privileged setting in which a centrally trained policy succeeds often enough for the federation's
success to be compared with it. ``sim-tasks`` is privileged alike, its owners teaching different
tasks (configs/sim-tasks-registry.toml): every model's success is also tabled task by task in each
set whose conditions hold several tasks (the server's, and an owner's who teaches two).

    python -m zk0.bench study [--settings mild noniid sim sim-cube sim-tasks] [--rounds 8] [--local-steps 20]
        [--clients 4] [--model tiny] [--lr 8e-3] [--federation-lr LR] [--federations FedProx FedAvg Nesterov ...]
        [--server-lr LR] [--server-momentum M] [--demos 30] [--sim-episodes 10] [--personal-steps N]
        [--new-owner NAME] [--new-demos 10] [--new-steps 300]
        [--output-dir outputs/bench-study]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

from zk0.artifacts.resume import find_resume_point
from zk0.bench.models import (
    EVAL_ALL,
    NEW_ALONE,
    NEW_FROM_GLOBAL,
    NEW_OWNER,
    SERVER,
    Weights,
    centralised,
    closed_loop_all,
    continuation,
    evaluate_all,
    evaluation_sets,
    federate,
    fine_tuned,
    generate,
    local_only,
    new_owner,
)  # fmt: skip
from zk0.bench.stash import Stash
from zk0.bench.study_tables import (
    EQUAL_STEPS,
    FEDERATIONS,
    chart,
    federations,
    over_seeds,
    print_over_seeds,
    print_setting,
    sim_summary,
    summary,
)
from zk0.common.errors import OneSentenceParser, Zk0Error, positive
from zk0.config import OFFLINE_MODELS, POLICIES, RunConfig
from zk0.data.registry import PROJECT_ROOT, load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import PolicyBundle, snapshot
from zk0.sim.tasks import SIM_SPECS

SETTINGS = {
    "mild": "",
    "noniid": str(PROJECT_ROOT / "configs" / "noniid-registry.toml"),
    "sim": str(PROJECT_ROOT / "configs" / "sim-registry.toml"),  # judged by success rate in the simulator too
    "sim-cube": str(PROJECT_ROOT / "configs" / "sim-cube-registry.toml"),  # the same, told where the cube is
    # owners who teach different tasks, told where the cubes and their places are: success task by task
    "sim-tasks": str(PROJECT_ROOT / "configs" / "sim-tasks-registry.toml"),
}
SIM_SETTINGS = ("sim", "sim-cube", "sim-tasks")


def study_run(args: argparse.Namespace, registry: str, seed: int = RunConfig.seed) -> RunConfig:
    """The in-process baselines' config: the federation's own keys (zk0.bench.models.federate)."""
    server = load_registry(registry).server.name
    return RunConfig(
        seed=seed,
        server_eval_dataset=server,
        num_server_rounds=args.rounds,
        local_steps=args.local_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        eval_batches=EVAL_ALL,
        registry=registry,
        model=args.model,
        policy=args.policy,
        min_train_clients=args.clients,
        personal_steps=args.personal_steps,
    )


def progress(setting: str, started: float) -> Callable[[str], None]:
    """Says one line as each model is trained or judged: a sim study runs for an hour before its tables."""
    return lambda done: print(f"  {setting}: {done} ({time.perf_counter() - started:.0f} s)", flush=True)


def federated_models(
    args: argparse.Namespace,
    setting: str,
    seed: int,
    server: PolicyBundle,
    stash: Stash,
    say: Callable[[str], None],
) -> dict[str, tuple[Weights, dict]] | None:
    """Each of ``--federations`` through ``flwr run`` with training seed ``seed``: each final
    global model and the run's history, kept in ``stash`` (None, after Flower's log and one
    sentence, if a federation failed)."""
    registry = SETTINGS[setting]
    models = {}
    for label in args.federations:
        optimiser = FEDERATIONS[label]
        keys = {
            "proximal-mu": args.proximal_mu if label == "FedProx" else 0.0,
            "server-optimiser": optimiser,
            "server-lr": args.server_lr if args.server_lr and optimiser != "fedavg" else 0.0,
            "server-momentum": args.server_momentum,
            "registry": registry,
            "server-eval-dataset": study_run(args, registry).server_eval_dataset,
            "eval-frequency": args.rounds,
            "lr": args.federation_lr,
            "model": args.model,
            "policy": args.policy,
            "seed": seed,
        }
        name = f"federation {label}"
        if not stash.has(name):
            folder = stash.folder / f"federation-{label.lower()}"
            keys = {**keys, **continuation(folder)}  # a stopped one continues from its last round
            history = federate(args, args.rounds, str(folder.relative_to(Path(args.output_dir))), **keys)
            if history is None:
                return None
            stash.figures(name, lambda h=history: h)
        history = stash.figures(name, dict)
        final = stash.weights(
            label, lambda h=history: find_resume_point(h["run-dir"]).trainable(server).to_torch_state_dict()
        )
        models[label] = (final, history)
        say(f"federation {label} trained")
    return models


# What the models of a study depend on: a folder holding models trained otherwise is refused.
TRAINING_KEYS = ("rounds", "local_steps", "batch_size", "model", "lr", "federation_lr", "proximal_mu", "federations",
                 "server_lr", "server_momentum", "clients", "demos", "personal_steps", "wire_dtype", "policy")  # fmt: skip
# What a new owner's models depend on (kept in the stash under names that say it, so adding one to a
# study keeps the models trained before it).
NEW_OWNER_KEYS = ("new_owner", "new_demos", "new_steps")
# A key that studies recorded before it existed, and its value then (they trained SmolVLA, no new owner).
BEFORE_KEYS = {"policy": "smolvla", "new_owner": None, "new_demos": 10, "new_steps": 300}


def training_settings(args: argparse.Namespace) -> dict:
    """What ``args`` trains with, as a study folder records it: a key at its value from before the
    key existed is left out, so folders and figures recorded then are still this command's."""
    return {k: vars(args)[k] for k in TRAINING_KEYS if k not in BEFORE_KEYS or vars(args)[k] != BEFORE_KEYS[k]}


def rollout_plan(models: list[str], clients: int) -> dict[str, list[str]]:
    """Which models are rolled out in which conditions: every model in the server's span (the
    untrained start only there); in each owner's own, every model but the equal-steps baseline
    (an offline question) and the other owners' personal models (no one else runs them); a new
    owner's two models only in its own, beside the federations'."""

    newcomer = [m for m in models if m in (NEW_FROM_GLOBAL, NEW_ALONE)]

    def mine(label: str, column: str) -> bool:
        return not label.startswith("personal ") or column == f"client {label.split()[-1]}"

    plan = {f"client {c}": [m for m in models if m not in ("start", EQUAL_STEPS, *newcomer) and mine(m, f"client {c}")]
            for c in range(clients)}  # fmt: skip
    plan[SERVER] = [m for m in models if m not in (EQUAL_STEPS, *newcomer)]
    if newcomer:  # the new owner's two models beside the global one(s), in its own conditions alone
        plan[NEW_OWNER] = [*federations(dict.fromkeys(models)), *newcomer]
    return plan


def study_stash(args: argparse.Namespace, setting: str, seed: int) -> Stash:
    """Where one setting's models of training seed ``seed`` are kept (refused if trained otherwise)."""
    return Stash(Path(args.output_dir) / setting / f"seed-{seed}", training_settings(args))


def run_seed(args: argparse.Namespace, setting: str, seed: int) -> dict | None:
    """Train every model of one setting with training seed ``seed`` and evaluate each on every
    evaluation set (None: a federation failed). What an earlier run of the same command finished is
    taken from its folder (zk0.bench.stash), so a stopped study continues."""
    registry_path = SETTINGS[setting]
    registry = load_registry(registry_path)
    run = study_run(args, registry_path, seed)
    generate(registry, args.demos)
    started = time.perf_counter()
    stash = study_stash(args, setting, seed)
    cameras = registry.model_cameras()
    sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients[: args.clients])]
    columns = evaluation_sets(sessions, registry, run)
    start = snapshot(sessions[0].bundle)
    say = progress(f"{setting}, seed {seed}", started)
    federations = federated_models(args, setting, seed, columns[SERVER][0], stash, say)
    if federations is None:
        return None
    models: dict[str, Weights] = {"start": start, **{label: w for label, (w, _) in federations.items()}}

    def pooled(wide: bool = False) -> Weights:
        weights, samples = centralised(sessions, run, start, cameras, wide=wide)
        if not wide:  # kept before the weights: kept weights always have their counts
            stash.figures("centralised samples", lambda: samples)
        return weights

    models["centralised"] = stash.weights("centralised", pooled)
    seen = stash.figures("centralised samples", dict)
    say("centralised trained")
    for session in sessions:
        models[f"local {session.index}"] = stash.weights(
            f"local {session.index}", lambda s=session: local_only(s, run, start)
        )
    say("local-only models trained")
    if args.personal_steps:  # each owner's personal model, and its own model given the same extra steps
        federated = models[args.federations[0]]
        for session in sessions:
            alone = models[f"local {session.index}"]
            models[f"personal {session.index}"] = stash.weights(
                f"personal {session.index}", lambda s=session: fine_tuned(s, run, federated)
            )
            models[f"local {session.index}"] = stash.weights(
                f"local {session.index} fine-tuned", lambda s=session, w=alone: fine_tuned(s, run, w)
            )
        say(f"personal models ({args.federations[0]} fine-tuned) and local-only models fine-tuned alike")
    models[EQUAL_STEPS] = stash.weights(EQUAL_STEPS, lambda: pooled(wide=True))
    say("equal steps trained")
    matrix = evaluate_all(models, columns, run, stash)
    if args.new_owner:  # judged in closed loop in its own conditions only: its models join after the matrix
        federated = models[args.federations[0]]
        newcomer, trained, newcomer_stash = new_owner(args, run, cameras, len(sessions), federated, start, stash)
        columns[NEW_OWNER] = (newcomer.bundle, newcomer.split, newcomer.eval_batches)
        models |= trained
        say(f"the new owner's models trained ({args.new_owner}, {args.new_demos} demonstrations)")
    say("every model evaluated on every held-out set")
    closed_loop = {}
    if setting in SIM_SETTINGS:
        plan = rollout_plan(list(models), len(sessions))
        newcomer_plan = {NEW_OWNER: plan.pop(NEW_OWNER)} if NEW_OWNER in plan else {}
        success = closed_loop_all(plan, models, columns, args.sim_episodes, RunConfig.seed, say, stash)
        if newcomer_plan:  # kept in the new owner's own folder (another new owner is other rollouts)
            rolled = closed_loop_all(
                newcomer_plan, models, columns, args.sim_episodes, RunConfig.seed, say, newcomer_stash
            )
            for label, row in rolled.items():
                success.setdefault(label, {}).update(row)
        closed_loop = {"success": success, "success-summary": sim_summary(success, len(sessions))}
    return {
        **closed_loop,
        "seed": seed,
        "registry": registry_path or "pyproject.toml",
        "clients": {f"client {s.index}": s.split.entry.name for s in sessions},
        **({"new-owner": args.new_owner} if args.new_owner else {}),
        "server": run.server_eval_dataset,
        "matrix": matrix,
        "summary": summary(matrix, len(sessions)),
        "centralised-samples-from": seen,
        "federations": {
            label: {
                "run-dir": h["run-dir"],
                "wall-s": h["wall-s"],
                "server-evaluate": [r["server-evaluate"] for r in h["rounds"] if r.get("server-evaluate")],
            }
            for label, (_, h) in federations.items()
        },
        "wall-s": time.perf_counter() - started,
    }


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench study", description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=["mild", "noniid"])
    parser.add_argument("--rounds", type=positive(int), default=8)
    parser.add_argument("--local-steps", type=positive(int), default=20)
    parser.add_argument("--batch-size", type=positive(int), default=8)
    parser.add_argument("--policy", default="smolvla", choices=POLICIES, help="the lerobot policy type every model is")
    parser.add_argument("--model", default="tiny", choices=OFFLINE_MODELS, help="the offline model (sim: tiny-128)")
    parser.add_argument("--lr", type=positive(float), default=8e-3, help="every model's (the best tried for each)")
    parser.add_argument(
        "--federation-lr",
        type=positive(float),
        help="the federation's learning rate (default: --lr, as the baselines')",
    )
    parser.add_argument("--proximal-mu", type=positive(float), default=0.01, help="FedProx's mu")
    parser.add_argument(
        "--federations",
        nargs="+",
        choices=list(FEDERATIONS),
        default=["FedProx", "FedAvg", "FedAvgM", "Nesterov", "FedAdam"],
        help="the federations to train (FedProx: plain averaging with --proximal-mu; the rest: proximal-mu 0)",
    )
    parser.add_argument("--server-lr", type=positive(float), help="the server optimisers' (default: each one's own)")
    parser.add_argument("--server-momentum", type=float, default=RunConfig.server_momentum)
    parser.add_argument("--clients", type=positive(int), default=4)
    parser.add_argument("--demos", type=positive(int), default=30, help="demonstrations per simulated client (sim)")
    parser.add_argument(
        "--sim-episodes", type=positive(int), default=10, help="closed-loop episodes per model and condition (sim)"
    )
    parser.add_argument(
        "--personal-steps", type=int, default=0,
        help="also each owner's personal model: the first federation's model fine-tuned this many steps on its own "
        "data at a quarter of --lr (zk0.federation.personal), and each local-only model fine-tuned alike; 0 = none",
    )  # fmt: skip
    parser.add_argument(
        "--new-owner", metavar="NAME",
        help="a simulated set-up whose owner joins once the federation is trained (e.g. sim-so101-owner-16-sort-cube in "
        "sim-tasks, whose owners teach no sort): the global model fine-tuned on its demonstrations against a model "
        "trained on them from the start, rolled out in its conditions (sim settings)",
    )  # fmt: skip
    parser.add_argument("--new-demos", type=positive(int), default=10, help="the new owner's demonstrations")
    parser.add_argument("--new-steps", type=positive(int), default=300, help="steps each new-owner model trains")
    parser.add_argument(
        "--seeds", nargs="+", type=int, default=[RunConfig.seed],
        help="training seeds: every model is trained once per seed (the frozen backbone's start, the data order, "
        "the noise) and rolled out on the same seeded episodes; the tables give the mean, the spread and intervals",
    )  # fmt: skip
    parser.add_argument(
        "--seeds-from", metavar="JSON",
        help="an earlier study's JSON (trained with the same settings): the seeds it has are taken from it, with "
        "every rollout's outcomes, instead of being trained again; the rest are trained and the tables cover all",
    )  # fmt: skip
    parser.add_argument("--wire-dtype", default="bfloat16", choices=["bfloat16", "float32"])
    parser.add_argument("--output-dir", default="outputs/bench-study")
    parser.add_argument("--json", help="the figures (default: <output-dir>/study.json)")
    parser.add_argument("--chart", help="the PNG chart (default: <output-dir>/study.png)")
    return parser


def earlier_seeds(args: argparse.Namespace) -> dict[str, dict[int, dict]]:
    """The per-seed figures of ``--seeds-from`` (setting -> seed -> figures), if it was trained and
    rolled out as this command would (a ``Zk0Error`` naming the first setting that differs)."""
    if not args.seeds_from:
        return {}
    try:
        earlier = json.loads(Path(args.seeds_from).read_text())
        settings, results = earlier["settings"], earlier["results"]
    except (OSError, ValueError, KeyError, TypeError):
        raise Zk0Error(
            f"--seeds-from {args.seeds_from!r} is not a study's JSON (python -m zk0.bench study --json)."
        ) from None
    for key in (*TRAINING_KEYS, "sim_episodes", *NEW_OWNER_KEYS):
        mine, theirs = json.loads(json.dumps(vars(args)[key])), settings.get(key, BEFORE_KEYS.get(key))
        if theirs != mine:
            raise Zk0Error(
                f"--seeds-from {args.seeds_from!r} was trained with {key} = {theirs!r}, not {mine!r}; "
                "its seeds cannot be tabled with these."
            )
    return {setting: {int(seed): run for seed, run in result["seeds"].items()} for setting, result in results.items()}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.federation_lr = args.federation_lr or args.lr
    if args.personal_steps < 0:
        parser.error(f"--personal-steps got {args.personal_steps}; expected 0 (none) or more")
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        parser.error(f"--seeds got {' '.join(map(str, args.seeds))}; expected different seeds, each 0 or more")
    if args.new_owner and (args.new_owner not in SIM_SPECS or not set(args.settings) <= set(SIM_SETTINGS)):
        parser.error(
            f"--new-owner got {args.new_owner!r}; expected a simulated set-up ({', '.join(SIM_SPECS.described())}) "
            f"and only the simulated settings ({', '.join(SIM_SETTINGS)})"
        )
    for setting in args.settings:
        available = len(load_registry(SETTINGS[setting]).clients)
        if args.clients > available:
            parser.error(f"--clients got {args.clients}; the {setting} setting has {available} client datasets")
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    try:  # before any training: a folder of models trained otherwise, or figures from another study
        earlier = earlier_seeds(args)
        for setting in args.settings:
            for seed in args.seeds:
                if seed not in earlier.get(setting, {}):
                    study_stash(args, setting, seed)
    except Zk0Error as err:
        print(f"[zk0] {err}", file=sys.stderr)
        return 2

    results = {}
    for setting in args.settings:
        runs = []
        for seed in args.seeds:
            run = earlier.get(setting, {}).get(seed) or run_seed(args, setting, seed)
            if run is None:
                return 1
            print_setting(setting, run, args)
            runs.append(run)
        results[setting] = {"over-seeds": over_seeds(runs, args.clients), "seeds": {str(r["seed"]): r for r in runs}}
        if "success" in runs[0] and len(runs) > 1:
            print_over_seeds(setting, results[setting]["over-seeds"])
    json_path, chart_path = Path(args.json or out / "study.json"), Path(args.chart or out / "study.png")
    json_path.write_text(json.dumps({"settings": vars(args), "results": results}, indent=2))
    chart({setting: result["over-seeds"] for setting, result in results.items()}, chart_path)
    print(f"\nfigures: {json_path}; chart: {chart_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
