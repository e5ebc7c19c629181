"""Study: does federating help? The federation against centralised and local-only training.

On the same synthetic clients, model, batch size and number of samples, with one learning rate
(``--lr``; ``--federation-lr`` gives the federation another), it trains

- the federation through the real app (``flwr run``, simulated clients), once per
  ``--federations`` entry: FedProx (plain averaging with ``--proximal-mu``), and with
  ``proximal-mu = 0`` FedAvg and each server optimiser (FedAvgM, Nesterov, FedAdam, FedYogi:
  zk0.server_optimisers, at their defaults or ``--server-lr``/``--server-momentum``);
- **centralised**: one policy and one optimizer on every client's training episodes pooled,
  taking batches from each client's own loader in turn, each preprocessed with that client's
  own processors (camera mapping, normalisation), for as many steps as all clients take in the
  federation together (zk0.training.PooledTrainer);
- **equal steps**: the same pooled training for only the federation's sequential steps (rounds x
  local steps), each on a batch from every client together (batch = clients x batch): the same
  samples again, so it splits "fewer sequential steps" from "federating";
- **local-only**: each client alone, for the steps it takes in the federation;

- with ``--personal-steps N``, **personal** *i*: the first federation's model fine-tuned N steps on
  client *i*'s own data as a federation's client fine-tunes its personal model (zk0.personal, a
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
from zk0.client import build_client
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.errors import OneSentenceParser, positive
from zk0.policy import PolicyBundle, snapshot
from zk0.rates import compare_text
from zk0.registry import PROJECT_ROOT, load_registry
from zk0.resume import find_resume_point

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


def study_run(args: argparse.Namespace, registry: str) -> RunConfig:
    """The in-process baselines' config: the federation's own keys (zk0.bench.learning.federate)."""
    server = next(e.name for e in load_registry(registry).entries if e.role == "server")
    return RunConfig(
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
    args: argparse.Namespace, setting: str, registry: str, server: PolicyBundle, say: Callable[[str], None]
) -> dict[str, tuple[Weights, dict]] | None:
    """Each of ``--federations`` through ``flwr run``: each final global model and the run's history
    (None, after Flower's log and one sentence, if a federation failed)."""
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
        }
        history = federate(args, args.rounds, f"{setting}-{label.lower()}", **keys)
        if history is None:
            return None
        final = find_resume_point(history["run-dir"]).trainable(server).to_torch_state_dict()
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


def run_setting(args: argparse.Namespace, setting: str) -> dict | None:
    """Train every model of one setting and evaluate each on every evaluation set (None: a federation failed)."""
    registry_path = SETTINGS[setting]
    registry = load_registry(registry_path)
    run = study_run(args, registry_path)
    generate(registry, args.demos)
    started = time.perf_counter()
    cameras = registry.model_cameras()
    sessions = [build_client(run, entry, cameras, i) for i, entry in enumerate(registry.clients[: args.clients])]
    columns = evaluation_sets(sessions, registry, run)
    start = snapshot(sessions[0].bundle)
    say = progress(setting, started)
    federations = federated_models(args, setting, registry_path, columns[SERVER][0], say)
    if federations is None:
        return None
    models: dict[str, Weights] = {"start": start, **{label: w for label, (w, _) in federations.items()}}
    models["centralised"], seen = centralised(sessions, run, start, cameras)
    say("centralised trained")
    for session in sessions:
        models[f"local {session.index}"] = local_only(session, run, start)
    say("local-only models trained")
    if args.personal_steps:  # each owner's personal model, and its own model given the same extra steps
        federated = models[args.federations[0]]
        for session in sessions:
            models[f"personal {session.index}"] = fine_tuned(session, run, federated)
            models[f"local {session.index}"] = fine_tuned(session, run, models[f"local {session.index}"])
        say(f"personal models ({args.federations[0]} fine-tuned) and local-only models fine-tuned alike")
    models[EQUAL_STEPS], _ = centralised(sessions, run, start, cameras, wide=True)  # last: the others' data order stays
    say("equal steps trained")
    matrix = evaluate_all(models, columns, run)
    say("every model evaluated on every held-out set")
    closed_loop = {}
    if setting in SIM_SETTINGS:
        success = closed_loop_all(models, columns, run, args.sim_episodes, say)
        closed_loop = {"success": success, "success-summary": sim_summary(success, len(sessions))}
    return {
        **closed_loop,
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
        f"\nsetting {setting}: {len(result['clients'])} clients ({', '.join(result['clients'].values())}), "
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
        "data at a quarter of --lr (zk0.personal), and each local-only model fine-tuned alike; 0 = none",
    )  # fmt: skip
    parser.add_argument("--wire-dtype", default="bfloat16", choices=["bfloat16", "float32"])
    parser.add_argument("--output-dir", default="outputs/bench-study")
    parser.add_argument("--json", help="the figures (default: <output-dir>/study.json)")
    parser.add_argument("--chart", help="the PNG chart (default: <output-dir>/study.png)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.federation_lr = args.federation_lr or args.lr
    if args.personal_steps < 0:
        parser.error(f"--personal-steps got {args.personal_steps}; expected 0 (none) or more")
    for setting in args.settings:
        available = len(load_registry(SETTINGS[setting]).clients)
        if args.clients > available:
            parser.error(f"--clients got {args.clients}; the {setting} setting has {available} client datasets")
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)

    results = {}
    for setting in args.settings:
        result = run_setting(args, setting)
        if result is None:
            return 1
        results[setting] = result
        print_setting(setting, results[setting], args)
    json_path, chart_path = Path(args.json or out / "study.json"), Path(args.chart or out / "study.png")
    json_path.write_text(json.dumps({"settings": vars(args), "results": results}, indent=2))
    chart(results, chart_path)
    print(f"\nfigures: {json_path}; chart: {chart_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
