"""What a study concludes and shows: its targets (federation against centralised and against each
owner training alone, offline and in closed loop), the statistics over training seeds, the tables
it prints and the chart it draws. zk0.bench.study trains and judges the models; this module only
reads their figures.
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from zk0.bench.models import NEW_ALONE, NEW_FROM_GLOBAL, NEW_OWNER, SERVER
from zk0.learning.rates import bootstrap, compare_text, mcnemar, rate_metrics

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


def print_setting(setting: str, result: dict, args: argparse.Namespace) -> None:
    matrix = result["matrix"]
    columns = list(next(iter(matrix.values())))
    print(
        f"\nsetting {setting}, training seed {result['seed']}: {len(result['clients'])} clients ({', '.join(result['clients'].values())}), "
        f"server set {result['server']}; {args.policy} {args.model}, {args.rounds} rounds x {args.local_steps} steps, "
        f"batch {args.batch_size}, lr {args.lr} (federation {args.federation_lr})"
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
    columns = every_column(success)
    print(f"closed-loop success in each set's conditions, % [95% interval] of {episodes_text(success)}")
    print(f"{'':<12}" + "".join(f"{c:>14}" for c in columns))
    for label, row in success.items():
        cells = [rate_cell(row[c]) if c in row else "-" for c in columns]
        print(f"{label:<12}" + "".join(f"{cell:>14}" for cell in cells))
    print_tasks(success)
    for column in [c for c in columns if c.startswith("client ")]:
        owner = column.split()[-1]
        models = [*federations(success), f"personal {owner}"]
        for label, other in [(m, o) for m in models for o in (f"local {owner}", "centralised") if m in success]:
            if "outcomes" in success[label][column] and "outcomes" in success[other][column]:
                paired = compare_text(success[label][column]["outcomes"], success[other][column]["outcomes"])
                print(f"  {label} against {other} in {column}'s conditions: {paired}")
    if NEW_OWNER in success.get(NEW_FROM_GLOBAL, {}):
        paired = compare_text(
            success[NEW_FROM_GLOBAL][NEW_OWNER]["outcomes"], success[NEW_ALONE][NEW_OWNER]["outcomes"]
        )
        print(
            f"  the new owner: the global model fine-tuned on its demonstrations against trained on them alone: {paired}"
        )
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


def task_rates(rates: dict) -> dict[str, dict]:
    """A multi-task set's rollout, task by task: each task's success with its interval (from the
    outcomes and the ``kinds`` they are of, or as ``over_seeds`` pooled them); empty for one task."""
    if "tasks" in rates:
        return rates["tasks"]
    if "kinds" not in rates:
        return {}
    return {
        kind: rate_metrics([o for o, k in zip(rates["outcomes"], rates["kinds"], strict=True) if k == kind])
        for kind in dict.fromkeys(rates["kinds"])
    }


def print_tasks(success: dict[str, dict[str, dict]]) -> None:
    """For each set whose conditions hold several tasks, every model's success in each task."""
    columns = list(dict.fromkeys(c for row in success.values() for c, rates in row.items() if task_rates(rates)))
    for column in columns:
        rows = {label: task_rates(row[column]) for label, row in success.items() if column in row}
        kinds = list(next(iter(rows.values())))
        print(f"success in each task of {column}'s conditions, % [95% interval]")
        print(f"{'':<22}" + "".join(f"{k:>20}" for k in kinds))
        for label, tasks in rows.items():
            print(f"{label:<22}" + "".join(f"{rate_cell(tasks[k]):>20}" for k in kinds))


def episodes_text(success: dict[str, dict[str, dict]], seeded: str = "seeded ") -> str:
    """``100 seeded episodes``, or in a multi-task set ``100 seeded episodes per task``: how many
    episodes each rate in the server's conditions is over (centralised is rolled out there)."""
    server = success["centralised"][SERVER]
    tasks = task_rates(server)
    episodes = int(next(iter(tasks.values()))["episodes"] if tasks else server["episodes"])
    return f"{episodes} {seeded}episodes" + (" per task" if tasks else "")


def every_column(success: dict[str, dict[str, dict]]) -> list[str]:
    """The conditions any model was rolled out in: the owners', the server's, a new owner's."""
    return list(dict.fromkeys(column for row in success.values() for column in row))


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
        if kinds := first["success"][label][column].get("kinds"):  # each task over every seed's episodes
            every = {"outcomes": sum(rows, []), "kinds": kinds * len(rows)}
            success[label][column]["tasks"] = {  # "episodes" as the overall figure says it: per seed
                kind: {**rates, "episodes": rates["episodes"] / len(rows)} for kind, rates in task_rates(every).items()
            }
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
    if f"{NEW_FROM_GLOBAL} | {NEW_OWNER}" in outcomes:  # what the federation gives an owner who joins late
        pairs = [sum(outcomes[f"{m} | {NEW_OWNER}"], []) for m in (NEW_FROM_GLOBAL, NEW_ALONE)]
        targets["new-owner-points"] = {
            **figure(lambda v: 100 * (rate(v, NEW_FROM_GLOBAL, NEW_OWNER) - rate(v, NEW_ALONE, NEW_OWNER))),
            "mcnemar-p": mcnemar(*pairs),
        }
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
    columns = every_column(success)
    print(f"\nsetting {setting} over training seeds {seeds}: closed-loop success, mean % over the seeds "
          f"[95% interval of every seed's {episodes_text(success, seeded='')}] (lowest-highest seed)")  # fmt: skip
    print(f"{'':<22}" + "".join(f"{c:>20}" for c in columns))
    for label, row in success.items():
        cells = [seed_cell(row[c]) if c in row else "-" for c in columns]
        print(f"{label:<22}" + "".join(f"{cell:>20}" for cell in cells))
    print_tasks(success)
    t = result["success-summary"]
    for label, f in t["vs-centralised"].items():
        print(f"{label} / centralised, success in the server's conditions: {figure_text(f)}")
    for label, f in t["vs-centralised-every-set"].items():
        print(f"{label} / centralised, success over every set's conditions: {figure_text(f)} (target >= 0.9)")
    if "new-owner-points" in t:
        f = t["new-owner-points"]
        print(f"the new owner, fine-tuned from the global model against trained alone: {figure_text(f, points=True)} "
              f"(McNemar p = {f['mcnemar-p']:.2g} over every seed's pairs)")  # fmt: skip
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
