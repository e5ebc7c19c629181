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
success to be compared with it.

    python -m zk0.bench study [--settings mild noniid sim sim-cube] [--rounds 8] [--local-steps 20]
        [--clients 4] [--model tiny] [--lr 8e-3] [--federation-lr LR] [--federations FedProx FedAvg Nesterov ...]
        [--server-lr LR] [--server-momentum M] [--demos 30] [--sim-episodes 10] [--personal-steps N]
        [--output-dir outputs/bench-study]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from zk0.bench.models import (
    EVAL_ALL,
    SERVER,
    Weights,
    centralised,
    closed_loop_all,
    evaluate_all,
    evaluation_sets,
    federate,
    fine_tuned,
    generate,
    local_only,
)  # fmt: skip
from zk0.bench.stash import Stash
from zk0.common.errors import OneSentenceParser, Zk0Error, positive
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.data.registry import PROJECT_ROOT, load_registry
from zk0.federation.client import build_client
from zk0.learning.policy import PolicyBundle, snapshot
from zk0.learning.rates import bootstrap, compare_text, mcnemar, rate_metrics
from zk0.outputs.resume import find_resume_point

SETTINGS = {
    "mild": "",
    "noniid": str(PROJECT_ROOT / "configs" / "noniid-registry.toml"),
    "sim": str(PROJECT_ROOT / "configs" / "sim-registry.toml"),  # judged by success rate in the simulator too
    "sim-cube": str(PROJECT_ROOT / "configs" / "sim-cube-registry.toml"),  # the same, told where the cube is
}
SIM_SETTINGS = ("sim", "sim-cube")
EQUAL_STEPS = "equal steps"  # centralised at the federation's sequential steps, batch = clients x batch
# The study's federations: label -> server-optimiser (only FedProx has a proximal term).
FEDERATIONS = {
    "FedProx": "fedavg",
    "FedAvg": "fedavg",
    "FedAvgM": "fedavgm",
    "Nesterov": "nesterov",
    "FedAdam": "fedadam",
    "FedYogi": "fedyogi",
}


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
            "seed": seed,
        }
        name = f"federation {label}"
        if not stash.has(name):
            folder = stash.folder / f"federation-{label.lower()}"
            shutil.rmtree(folder, ignore_errors=True)  # what a stopped run left: a federation starts over
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


def federations(rows: dict) -> list[str]:
    """The federations among a matrix's rows, in the order they were trained."""
    return [label for label in rows if label in FEDERATIONS]


def against_local_only(values: dict[str, dict[str, float]], clients: int, better) -> dict:
    """Each federation against each local-only model on the other clients' sets (the mean of
    ``values``, model -> column -> figure), and whether it is ``better(federated, local)`` for all."""
    others = {}
    for c in range(clients):
        rest = [f"client {j}" for j in range(clients) if j != c]
        row = {label: statistics.mean(values[label][col] for col in rest) for label in federations(values)}
        row["local-only"] = statistics.mean(values[f"local {c}"][col] for col in rest)
        others[f"local {c}"] = row
    beats = {
        label: all(better(row[label], row["local-only"]) for row in others.values()) for label in federations(values)
    }
    return {"other-clients": others, "federation-beats-every-local": beats}


def sim_summary(success: dict[str, dict[str, dict]], clients: int) -> dict:
    """The sim targets: federated success / centralised success in the server's conditions, and the
    federation against each local-only model in the conditions that client never saw."""
    rate = {label: {c: v["success-rate"] for c, v in row.items()} for label, row in success.items()}
    central = rate["centralised"][SERVER]
    ratios = {label: rate[label][SERVER] / central if central else None for label in federations(rate)}
    summary = {"vs-centralised": ratios, **against_local_only(rate, clients, lambda fed, local: fed > local)}
    if "personal 0" in rate:  # what an owner gets on its own set-up: its personal model against alone
        own = {c: (rate[f"personal {c}"][f"client {c}"], rate[f"local {c}"][f"client {c}"],
                   rate["centralised"][f"client {c}"]) for c in range(clients)}  # fmt: skip
        summary["personal-minus-alone-points"] = statistics.mean(100 * (p - a) for p, a, _ in own.values())
        centralised_own = statistics.mean(c for _, _, c in own.values())
        summary["personal-vs-centralised-own"] = (
            statistics.mean(p for p, _, _ in own.values()) / centralised_own if centralised_own else None
        )
    return summary


def summary(matrix: dict[str, dict[str, dict]], clients: int) -> dict:
    """The study's two targets: federation vs centralised on the server set, and federation vs each
    local-only model on the other clients' held-out episodes."""
    mse = {label: {c: v["action-mse"] for c, v in row.items()} for label, row in matrix.items()}
    central, steps = mse["centralised"][SERVER], mse[EQUAL_STEPS][SERVER]
    return {
        "vs-centralised": {label: mse[label][SERVER] / central for label in federations(mse)},
        "equal-steps-vs-centralised": steps / central,
        "vs-equal-steps": {label: mse[label][SERVER] / steps for label in federations(mse)},
        **against_local_only(mse, clients, lambda fed, local: fed < local),
    }


# What the models of a study depend on: a folder holding models trained otherwise is refused.
TRAINING_KEYS = ("rounds", "local_steps", "batch_size", "model", "lr", "federation_lr", "proximal_mu", "federations",
                 "server_lr", "server_momentum", "clients", "demos", "personal_steps", "wire_dtype")  # fmt: skip


def rollout_plan(models: list[str], clients: int) -> dict[str, list[str]]:
    """Which models are rolled out in which conditions: every model in the server's span (the
    untrained start only there); in each owner's own, every model but the equal-steps baseline
    (an offline question) and the other owners' personal models (no one else runs them)."""

    def mine(label: str, column: str) -> bool:
        return not label.startswith("personal ") or column == f"client {label.split()[-1]}"

    plan = {f"client {c}": [m for m in models if m not in ("start", EQUAL_STEPS) and mine(m, f"client {c}")]
            for c in range(clients)}  # fmt: skip
    plan[SERVER] = [m for m in models if m != EQUAL_STEPS]
    return plan


def study_stash(args: argparse.Namespace, setting: str, seed: int) -> Stash:
    """Where one setting's models of training seed ``seed`` are kept (refused if trained otherwise)."""
    return Stash(Path(args.output_dir) / setting / f"seed-{seed}", {k: vars(args)[k] for k in TRAINING_KEYS})


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
    say("every model evaluated on every held-out set")
    closed_loop = {}
    if setting in SIM_SETTINGS:
        plan = rollout_plan(list(models), len(sessions))
        success = closed_loop_all(plan, models, columns, args.sim_episodes, RunConfig.seed, say, stash)
        closed_loop = {"success": success, "success-summary": sim_summary(success, len(sessions))}
    return {
        **closed_loop,
        "seed": seed,
        "registry": registry_path or "pyproject.toml",
        "clients": {f"client {s.index}": s.split.entry.name for s in sessions},
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


def print_setting(setting: str, result: dict, args: argparse.Namespace) -> None:
    matrix = result["matrix"]
    columns = list(next(iter(matrix.values())))
    print(
        f"\nsetting {setting}, training seed {result['seed']}: {len(result['clients'])} clients ({', '.join(result['clients'].values())}), "
        f"server set {result['server']}; {args.rounds} rounds x {args.local_steps} steps, batch {args.batch_size}, "
        f"lr {args.lr} (federation {args.federation_lr})"
    )
    for metric in ("action-mse", "policy-loss"):
        print(f"{metric:<12}" + "".join(f"{c:>11}" for c in columns))
        for label, row in matrix.items():
            print(f"{label:<12}" + "".join(f"{row[c][metric]:>11.4g}" for c in columns))
    s = result["summary"]
    for label, ratio in s["vs-centralised"].items():
        print(f"{label} / centralised, server action MSE: {ratio:.3f} (target <= 1.5 at 8 rounds, 1.1 at 24)")
    print(
        f"equal steps / centralised, server action MSE: {s['equal-steps-vs-centralised']:.3f} "
        "(what a quarter of the sequential steps costs with the same samples)"
    )
    for label, ratio in s["vs-equal-steps"].items():
        print(f"{label} / equal steps, server action MSE: {ratio:.3f} (what federating costs beyond that)")
    labels = federations(matrix)
    print(f"other clients' held-out episodes, mean action MSE (local-only vs {', '.join(labels)}):")
    for local, row in s["other-clients"].items():
        print(f"  {local:<8} {row['local-only']:>9.2f}" + "".join(f" {row[label]:>9.2f}" for label in labels))
    for label, beats in s["federation-beats-every-local"].items():
        print(f"{label} better than every local-only model on the other clients' held-out episodes: {beats}")
    if "success" in result:
        print_success(result)
    seen = ", ".join(f"{n} {k}" for k, n in result["centralised-samples-from"].items())
    print(f"centralised trained on samples from: {seen}; {result['wall-s']:.0f} s")


def print_success(result: dict) -> None:
    """The closed-loop matrix (success with its 95% interval), the paired comparisons on each
    owner's own conditions, and the sim targets."""
    success = result["success"]
    columns = list(success["centralised"])
    episodes = int(success["centralised"][SERVER]["episodes"])
    print(f"closed-loop success in each set's conditions, % [95% interval] of {episodes} seeded episodes")
    print(f"{'':<12}" + "".join(f"{c:>14}" for c in columns))
    for label, row in success.items():
        cells = [rate_cell(row[c]) if c in row else "-" for c in columns]
        print(f"{label:<12}" + "".join(f"{cell:>14}" for cell in cells))
    for column in columns[:-1]:
        owner = column.split()[-1]
        models = [*federations(success), f"personal {owner}"]
        for label, other in [(m, o) for m in models for o in (f"local {owner}", "centralised") if m in success]:
            if "outcomes" in success[label][column] and "outcomes" in success[other][column]:
                paired = compare_text(success[label][column]["outcomes"], success[other][column]["outcomes"])
                print(f"  {label} against {other} in {column}'s conditions: {paired}")
    s = result["success-summary"]
    for label, ratio in s["vs-centralised"].items():
        shown = "n/a (centralised 0%)" if ratio is None else f"{ratio:.2f}"
        print(f"{label} / centralised, success in the server's conditions: {shown} (target >= 0.9)")
    for label, beats in s["federation-beats-every-local"].items():
        print(f"{label} succeeds more than every local-only model in the conditions that client never saw: {beats}")
    if "personal-minus-alone-points" in s:
        ratio = s["personal-vs-centralised-own"]
        print(f"personal models against each owner alone, in the owner's own conditions: "
              f"{s['personal-minus-alone-points']:+.0f} points on average (target >= +20); / centralised there: "
              + ("n/a (centralised 0%)" if ratio is None else f"{ratio:.2f} (target >= 0.95)"))  # fmt: skip


def rate_cell(rates: dict) -> str:
    """``45 [36, 55]``: a success rate and its interval, in percent."""
    return f"{100 * rates['success-rate']:.0f} [{100 * rates['success-low']:.0f}, {100 * rates['success-high']:.0f}]"


def over_seeds(runs: list[dict], clients: int) -> dict:
    """One setting's figures over its training seeds: each model's mean action MSE per set and,
    in the simulator, each success rate's mean, its spread between seeds and the mean's Wilson
    interval (over every seed's episodes), and the targets with their bootstrap intervals."""
    first = runs[0]
    matrix = {label: {column: {metric: statistics.mean(r["matrix"][label][column][metric] for r in runs)
                               for metric in cells} for column, cells in row.items()}
              for label, row in first["matrix"].items()}  # fmt: skip
    result = {"seeds": [r["seed"] for r in runs], "matrix": matrix}
    if "success" not in first:
        return result
    outcomes = {f"{label} | {column}": [r["success"][label][column]["outcomes"] for r in runs]
                for label, row in first["success"].items() for column in row}  # fmt: skip
    success: dict[str, dict[str, dict]] = {}
    for name, rows in outcomes.items():
        label, column = name.split(" | ")
        rates = [sum(row) / len(row) for row in rows]
        pooled = rate_metrics(sum(rows, []))  # the mean over seeds: every seed has as many episodes
        success.setdefault(label, {})[column] = {
            **pooled, "episodes": len(rows[0]), "seeds": len(rows),
            "seed-min": min(rates), "seed-max": max(rates), "per-seed": rates,
        }  # fmt: skip
    result["success"] = success
    result["success-summary"] = targets_over_seeds(outcomes, clients, federations(first["success"]))
    return result


def targets_over_seeds(outcomes: dict[str, list[list[int]]], clients: int, labels: list[str]) -> dict:
    """The sim targets over the seeds, each with its bootstrap interval: every federation's success
    against centralised training's in the server's span and over all sets; each owner's personal
    model against the owner alone (points, each owner's McNemar p over every seed's pairs) and
    against centralised in the owner's own conditions."""

    def rate(v: dict, label: str, column: str) -> np.ndarray:
        return v[f"{label} | {column}"].mean(axis=(-2, -1))

    def figure(statistic) -> dict[str, float]:
        low, high = bootstrap(outcomes, statistic)
        with np.errstate(divide="ignore", invalid="ignore"):
            point = float(statistic({k: np.asarray(rows, dtype=float) for k, rows in outcomes.items()}))
        finite = lambda x: x if math.isfinite(x) else None  # noqa: E731  (JSON has no NaN)
        return {"value": finite(point), "low": finite(low), "high": finite(high)}

    columns = [*(f"client {c}" for c in range(clients)), SERVER]
    every = lambda v, label: sum(rate(v, label, c) for c in columns) / len(columns)  # noqa: E731
    targets = {
        "vs-centralised": {f: figure(lambda v, f=f: rate(v, f, SERVER) / rate(v, "centralised", SERVER)) for f in labels},
        "vs-centralised-every-set": {f: figure(lambda v, f=f: every(v, f) / every(v, "centralised")) for f in labels},
    }  # fmt: skip
    if f"personal 0 | {SERVER}" not in outcomes:
        return targets
    own = [(f"personal {c}", f"local {c}", f"client {c}") for c in range(clients)]
    targets["personal-minus-alone-points"] = figure(
        lambda v: 100 * sum(rate(v, p, c) - rate(v, a, c) for p, a, c in own) / clients
    )
    targets["personal-vs-centralised-own"] = figure(
        lambda v: sum(rate(v, p, c) for p, _, c in own) / sum(rate(v, "centralised", c) for *_, c in own)
    )
    targets["each-owner"] = {}
    for p, a, c in own:
        mine, alone = (sum(outcomes[f"{m} | {c}"], []) for m in (p, a))  # every seed's episodes, paired
        targets["each-owner"][c] = {
            "points": 100 * (sum(mine) - sum(alone)) / len(mine), "mcnemar-p": mcnemar(mine, alone),
        }  # fmt: skip
    targets["personal-in-server-span"] = figure(lambda v: sum(rate(v, p, SERVER) for p, _, _ in own) / clients)
    return targets


def print_over_seeds(setting: str, result: dict) -> None:
    """The closed-loop table over the training seeds and the targets, each with its interval."""
    seeds = ", ".join(map(str, result["seeds"]))
    success = result["success"]
    columns = list(success["centralised"])
    episodes = success["centralised"][SERVER]["episodes"]
    print(f"\nsetting {setting} over training seeds {seeds}: closed-loop success, mean % over the seeds "
          f"[95% interval of every seed's {episodes} episodes] (lowest-highest seed)")  # fmt: skip
    print(f"{'':<22}" + "".join(f"{c:>20}" for c in columns))
    for label, row in success.items():
        cells = [seed_cell(row[c]) if c in row else "-" for c in columns]
        print(f"{label:<22}" + "".join(f"{cell:>20}" for cell in cells))
    t = result["success-summary"]
    for label, f in t["vs-centralised"].items():
        print(f"{label} / centralised, success in the server's conditions: {figure_text(f)}")
    for label, f in t["vs-centralised-every-set"].items():
        print(f"{label} / centralised, success over every set's conditions: {figure_text(f)} (target >= 0.9)")
    if "personal-minus-alone-points" in t:
        print(f"personal models against each owner alone, own conditions: "
              f"{figure_text(t['personal-minus-alone-points'], points=True)} (target >= +20)")  # fmt: skip
        for column, own in t["each-owner"].items():
            print(
                f"  {column}: {own['points']:+.0f} points (McNemar p = {own['mcnemar-p']:.2g} over every seed's pairs)"
            )
        print(f"personal models / centralised, own conditions: {figure_text(t['personal-vs-centralised-own'])} "
              "(target >= 0.95)")  # fmt: skip
        print(f"personal models in the server's span: {figure_text(t['personal-in-server-span'], percent=True)}")


def seed_cell(rates: dict) -> str:
    """``57 [52, 63] (49-64)``: the mean over seeds, its (Wilson) interval, the lowest and highest seed."""
    return f"{rate_cell(rates)} ({100 * rates['seed-min']:.0f}-{100 * rates['seed-max']:.0f})"


def figure_text(f: dict, points: bool = False, percent: bool = False) -> str:
    """A target's figure with its interval: ``0.79 [0.71, 0.89]``, ``+24 [18, 30] points``, ``12% [8, 17]``."""
    if f["value"] is None:
        return "n/a (centralised 0%)"
    if points:
        return f"{f['value']:+.0f} [{f['low']:+.0f}, {f['high']:+.0f}] points"
    if percent:
        return f"{100 * f['value']:.0f}% [{100 * f['low']:.0f}, {100 * f['high']:.0f}]"
    return f"{f['value']:.2f} [{f['low']:.2f}, {f['high']:.2f}]"


def chart(results: dict[str, dict], path: Path) -> None:
    """One table per setting, models x evaluation sets: each cell's action MSE, coloured by how many
    times the best model's on that set it is (green: the best; red: ten times the best or more)."""
    fig = Figure(figsize=(5.5 * len(results), 4.8), layout="constrained")
    for ax, (setting, result) in zip(np.atleast_1d(fig.subplots(1, len(results))), results.items(), strict=True):
        matrix = result["matrix"]
        rows, columns = list(matrix), list(next(iter(matrix.values())))
        values = np.array([[matrix[r][c]["action-mse"] for c in columns] for r in rows])
        ratio = values / values.min(axis=0)
        image = ax.imshow(ratio, cmap="RdYlGn_r", norm=LogNorm(vmin=1.0, vmax=10.0), aspect="auto")
        for i, j in np.ndindex(values.shape):
            ax.text(j, i, f"{values[i, j]:.3g}", ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(columns)), [c.replace("client ", "client\n") for c in columns])
        ax.set_yticks(range(len(rows)), rows)
        ax.set_title(f"{setting}: action MSE on each held-out set", fontsize=10)
        bar = fig.colorbar(image, ax=ax, shrink=0.8, label="x the best model's MSE on that set")
        bar.set_ticks([1, 2, 3, 5, 10], labels=["1", "2", "3", "5", "10"])
    fig.savefig(path, dpi=110)


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench study", description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=["mild", "noniid"])
    parser.add_argument("--rounds", type=positive(int), default=8)
    parser.add_argument("--local-steps", type=positive(int), default=20)
    parser.add_argument("--batch-size", type=positive(int), default=8)
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
    for key in (*TRAINING_KEYS, "sim_episodes"):
        mine = json.loads(json.dumps(vars(args)[key]))
        if settings.get(key) != mine:
            raise Zk0Error(
                f"--seeds-from {args.seeds_from!r} was trained with {key} = {settings.get(key)!r}, not {mine!r}; "
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
