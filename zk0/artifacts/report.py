"""``report.html``: a run on one page, opened from disk, rewritten after every round like the charts.

What a robot owner asks of a run, in order: which model to use and how (``models/best`` and the
``lerobot-rollout`` command), how the rounds went (a table and the charts), how each client took
part (samples, losses, and every refusal with its sentence), and what the run was configured
with. Its numbers are the ones in ``metrics_history.json`` (each cell carries the exact value in
``data-value``); the charts are embedded as data URIs, so the file is whole on its own: no server,
no network, nothing to break when the folder is copied. Jinja2 renders it, with autoescaping on:
dataset names and refusal sentences come from users.
"""

from __future__ import annotations

import base64
from pathlib import Path

from jinja2 import Environment, StrictUndefined
from markupsafe import Markup

from zk0.artifacts.run_folder import CHARTS, SIM_CHARTS, clients_trained, write_text
from zk0.learning.rates import model_choice, per_task, success_text
from zk0.sim.tasks import SIM_SPECS, beyond_span

REPORT_FILE = "report.html"
ROLLOUT = (
    "lerobot-rollout --strategy.type=base \\\n"
    "  --robot.type=so101_follower --robot.port=/dev/ttyACM0 --robot.id=my_arm \\\n"
    '  --robot.cameras="{ camera1: {type: opencv, index_or_path: 0, width: 640, height: 480, fps: 30}, '
    'camera2: {type: opencv, index_or_path: 2, width: 640, height: 480, fps: 30} }" \\\n'
    '  --task="<the task, as your dataset words it>" --duration=60 \\\n'
    "  --policy.path=POLICY"
)

TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>zk0 run {{ name }}</title>
<style>
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 70em; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: right; }
th { background: #f4f4f4; } td.text, th.text { text-align: left; }
tr.best td { background: #eef8ee; font-weight: bold; }
pre { background: #f6f6f6; padding: 0.8em; overflow-x: auto; }
.charts img { max-width: 48%; margin: 0.5em 1%; } .refusal { color: #a00; } .outside-span { color: #a60; }
</style>
</head>
<body>
<h1>zk0 run {{ name }}</h1>
<p id="status">{{ status }}</p>

<h2>Best model</h2>
{% if best %}
<p id="best">Round {{ best.round }}{% if best.round == 0 %} (the starting model: no round beat it){% endif %}:
{% if "success-rate" in best %}success {{ success_text(best) }} episodes in the simulator (95% interval), {% endif %}
server action MSE {{ best["action-mse"]|num }}. It is a lerobot policy folder: <code>{{ best_path }}</code>.</p>
<p>Run it on an SO-101 with lerobot's own tool (SO-100: <code>--robot.type=so100_follower</code>; cameras and
task as in docs/robot-owners.md):</p>
<pre>{{ rollout }}</pre>
{% else %}
<p id="best">The server has evaluated no round yet, so there is no <code>models/best</code>.</p>
{% endif %}

<h2>What the server learns about an owner</h2>
<p id="privacy">{{ privacy }} zk0's docs/privacy.md says what each setting protects and what it costs.</p>

<h2>Rounds</h2>
<table id="rounds">
<tr>{% for column in round_columns %}<th>{{ column.title }}</th>{% endfor %}</tr>
{% for row in rounds %}
<tr{% if best and row.round == best.round %} class="best"{% endif %}>
{% for column in round_columns %}{{ cell(row.cells[column.key]) }}{% endfor %}
</tr>
{% endfor %}
</table>

{% if tasks %}
<h2>Success per task</h2>
<p>The global model rolled out in each task the server's set teaches, on the same seeded episodes every
round (success [95% interval] of episodes).</p>
<table id="tasks">
<tr><th>round</th>{% for kind in tasks %}<th>{{ kind }}</th>{% endfor %}</tr>
{% for row in task_rows %}
<tr{% if best and row.round == best.round %} class="best"{% endif %}><td>{{ row.round }}</td>
{% for kind in tasks %}{{ cell(row.cells[kind]) }}{% endfor %}</tr>
{% endfor %}
</table>
{% endif %}

{% if charts %}
<h2>Charts</h2>
<div class="charts">
{% for chart in charts %}<img src="data:image/png;base64,{{ chart.data }}" alt="{{ chart.title }}">{% endfor %}
</div>
{% endif %}
{% if videos %}
<h2>Simulator rollouts</h2>
{% for video in videos %}<p>{{ video.title }}<br><video controls width="480" src="{{ video.src }}"></video></p>{% endfor %}
{% endif %}

<h2>Clients</h2>
<table id="clients">
<tr><th>client</th><th class="text">dataset</th><th>from round</th><th>rounds trained</th><th>samples trained</th>
<th>last train loss</th><th>last evaluation action MSE</th>
{% if personal %}<th>its personal model's action MSE</th><th>global model's success in its own conditions</th>
<th>personal model's success there</th><th class="text">which model to run</th>{% endif %}<th>refusals</th></tr>
{% for client in clients %}
<tr><td>{{ client.index }}</td><td class="text">{{ client.dataset }}</td><td>{{ client.first }}</td><td>{{ client.rounds }}</td>
{{ cell(client.samples) }}{{ cell(client.loss) }}{{ cell(client.mse) }}
{% if personal %}{{ cell(client.personal_mse) }}{{ cell(client.own_success) }}{{ cell(client.personal_success) }}
<td class="text">{{ client.choice or "-" }}</td>{% endif %}
<td>{{ client.refusals|length }}</td></tr>
{% endfor %}
</table>
{% if personal %}
<p id="personal">Each owner's personal model (the global model fine-tuned on their own data, evaluated on the
same held-out episodes) is on their own machine, never sent: in the run's folder there, under their output
folder (in simulation, this folder; on a SuperNode, its <code>--output-dir</code>). Client <i>i</i> runs theirs with
<code>--policy.path=clients/client_&lt;i&gt;/models/personal</code> in the command above, from that run folder:</p>
<pre>{{ personal_rollout }}</pre>
{% endif %}
{% for warning in outside_span %}
<p class="outside-span">Client {{ warning.index }} ({{ warning.dataset }}) is outside the span the other owners
trained in: {{ warning.how }}. The federation met these conditions only in this owner's own frames, so the global
model may fail there (docs/learning.md measures how often, with and without <code>image-transforms</code>): judge it by
its success in its own conditions, and try its personal model.</p>
{% endfor %}
{% for client in clients %}{% for refusal in client.refusals %}
<p class="refusal">Round {{ refusal.round }}, client {{ client.index }} ({{ client.dataset }}), {{ refusal.phase }}: {{ refusal.reason }}</p>
{% endfor %}{% endfor %}

<h2>Configuration</h2>
<table id="config">
{% for key, value in config %}<tr><th class="text">{{ key }}</th><td class="text">{{ value }}</td></tr>{% endfor %}
</table>
<p>All of it, per round and per client, is in <code>server/metrics_history.json</code>; the logs are
<code>server/server.log</code> and <code>clients/client_&lt;i&gt;/client.log</code>.</p>
</body>
</html>
"""

ROUND_COLUMNS = [
    ("round", "round"),
    ("trained", "clients trained"),
    ("refused", "refused"),
    ("steps", "local steps taken"),
    ("late", "late (not counted)"),
    ("train-loss", "train loss"),
    ("client-mse", "clients' action MSE"),
    ("policy-loss", "server policy loss"),
    ("action-mse", "server action MSE"),
    ("success-rate", "success rate [95% interval] of episodes"),
    ("epsilon", "privacy spent (epsilon)"),
    ("wall-s", "seconds since start"),
]


def _num(value: float | int | None) -> str:
    """How the report prints a figure: 4 significant digits, '-' where there is none."""
    if value is None:
        return "-"
    return str(value) if isinstance(value, int) else f"{value:.4g}"


def _cell(value: float | int | tuple[float, str] | None):
    """A table cell with its figure as printed and, in ``data-value``, as in the JSON (a pair: the
    figure and how it is printed, such as a success rate with its interval)."""
    if value is None:
        return Markup("<td>-</td>")
    value, text = value if isinstance(value, tuple) else (value, _num(value))
    return Markup('<td data-value="{}">{}</td>').format(repr(value), text)


_ENV = Environment(autoescape=True, undefined=StrictUndefined, trim_blocks=True, lstrip_blocks=True)
_ENV.filters["num"] = _num
_TEMPLATE = _ENV.from_string(TEMPLATE, globals={"cell": _cell, "success_text": success_text})


def round_row(record: dict) -> dict:
    """One row of the rounds table, from a round's record in ``metrics_history.json``."""
    clients = record["clients"].values()
    server = record.get("server-evaluate", {})
    values = {
        "round": record["round"],
        "trained": clients_trained(record),
        "refused": sum("error" in c.get(phase, {}) for c in clients for phase in ("train", "evaluate")),
        "steps": steps_cell([int(c["train"]["local-steps"]) for c in clients if "local-steps" in c.get("train", {})]),
        "late": late_cell(record.get("late")),
        "train-loss": record.get("aggregate-train", {}).get("train-loss"),
        "client-mse": record.get("aggregate-evaluate", {}).get("action-mse"),
        "policy-loss": server.get("policy-loss"),
        "action-mse": server.get("action-mse"),
        "success-rate": (server["success-rate"], success_text(server)) if "success-rate" in server else None,
        "epsilon": epsilon_spent(record),
        "wall-s": record.get("wall-s"),
    }
    return {"round": record["round"], "cells": values}


def task_rows(history: dict) -> tuple[list[str], list[dict]]:
    """The tasks a multi-task server set teaches, and each evaluated round's success in each."""
    judged = [(r["round"], per_task(r.get("server-evaluate", {}))) for r in history["rounds"]]
    judged = [(number, tasks) for number, tasks in judged if tasks]
    kinds = list(dict.fromkeys(kind for _, tasks in judged for kind in tasks))
    rows = [
        {"round": number, "cells": {k: (t[k]["success-rate"], success_text(t[k])) if k in t else None for k in kinds}}
        for number, t in judged
    ]
    return kinds, rows


def epsilon_spent(record: dict) -> float | None:
    """The privacy spent once a round's model was released: owner-level DP's epsilon, or with
    record-level DP the largest any owner's demonstrations have spent (each owner's accountant)."""
    if "privacy" in record:
        return float(record["privacy"]["epsilon"])
    spent = [c["train"]["record-epsilon"] for c in record["clients"].values() if "record-epsilon" in c.get("train", {})]
    return max(spent) if spent else None


def privacy_sentence(history: dict, config: dict) -> str:
    """What the server received from each owner under the run's ``dp`` setting, and what it spent."""
    kind, budget, delta = config.get("dp", "off"), config.get("dp-epsilon-budget"), config.get("dp-delta")
    spent = [e for r in history["rounds"] if (e := epsilon_spent(r)) is not None]
    so_far = (
        f" Spent so far: epsilon {spent[-1]:.3g} of dp-epsilon-budget={budget:g} at delta {delta:g}." if spent else ""
    )
    if kind == "owner":
        return (
            "Owner-level differential privacy: the server received each owner's update in the clear, clipped it to "
            f"dp-clip={config['dp-clip']:g} and released only the noisy average, so the models this run wrote say "
            "little about whether any one owner took part." + so_far
        )
    if kind == "record":
        return (
            "Record-level differential privacy: each owner trained with DP-SGD on their own machine (every "
            f"demonstration's gradient clipped to dp-clip={config['dp-clip']:g}, noise added before the update left), "
            "so what the server received says little about any one demonstration."
            + so_far.replace("epsilon", "the largest epsilon of any owner", 1)
        )
    return (
        "Differential privacy is off (dp='off'): the server received each owner's update, alone and in the clear, "
        "every round; an update can leak the frames it was trained on."
    )


def steps_cell(steps: list[int]) -> tuple[int, str] | None:
    """The fewest and most local steps a round's clients took (a time budget makes them differ)."""
    if not steps:
        return None
    low, high = min(steps), max(steps)
    return low, str(low) if low == high else f"{low}-{high}"


def late_cell(late: dict | None) -> tuple[int, str] | None:
    """The clients whose update missed the round's deadline."""
    if not late:
        return None
    named = [f"client {i}" for i in late["clients"]] + [f"node {n}" for n in late["nodes"]]
    return len(named), ", ".join(named)


def client_rows(history: dict) -> list[dict]:
    """Each client that took part: from which round (an owner may join mid-run), rounds and samples
    trained, its latest losses, its refusals."""
    rows = []
    for index, dataset in history["clients"].items():
        trained_in = [r for r in history["rounds"] if "train" in r["clients"].get(index, {})]
        trained = [r["clients"][index]["train"] for r in trained_in]
        evaluated = [
            r["clients"][index]["evaluate"] for r in history["rounds"] if "evaluate" in r["clients"].get(index, {})
        ]
        ok = [t for t in trained if "error" not in t]
        scored = [e for e in evaluated if "error" not in e]
        personal = [e for e in scored if "personal-action-mse" in e]  # the rounds it fine-tuned in (personal-frequency)
        refusals = [
            {"round": r["round"], "phase": phase, "reason": r["clients"][index][phase]["error"]}
            for r in history["rounds"]
            for phase in ("train", "evaluate")
            if "error" in r["clients"].get(index, {}).get(phase, {})
        ]
        rows.append(
            {
                "index": int(index),
                "dataset": dataset,
                "first": min((r["round"] for r in trained_in), default="-"),
                "rounds": len(ok),
                "samples": sum(int(t.get("num-examples", 0)) for t in ok) if ok else None,
                "loss": ok[-1].get("train-loss") if ok else None,
                "mse": scored[-1].get("action-mse") if scored else None,
                "personal_mse": personal[-1]["personal-action-mse"] if personal else None,
                "own_success": _own_success(personal[-1], "own-") if personal else None,
                "personal_success": _own_success(personal[-1], "personal-own-") if personal else None,
                "choice": model_choice(personal[-1]) if personal else "",
                "refusals": refusals,
            }
        )
    return rows


def outside_span(history: dict) -> list[dict]:
    """Each simulated client whose room lies beyond the span of the other simulated clients' rooms,
    and how (zk0.sim.tasks.beyond_span): an owner lit more dimly than every other trains the only
    dim frames the federation sees, and a model that succeeds in the server's conditions may
    almost never succeed there. Real owners' rooms are not known to the server, so nothing is said."""
    simulated = {int(i): name for i, name in history["clients"].items() if name in SIM_SPECS}
    warnings = []
    for index, name in sorted(simulated.items()):
        others = [SIM_SPECS[other].task.look for i, other in simulated.items() if i != index]
        how = beyond_span(SIM_SPECS[name].task.look, others) if others else []
        if how:
            warnings.append({"index": index, "dataset": name, "how": "; ".join(how)})
    return warnings


def _own_success(evaluation: dict, prefix: str) -> tuple[float, str] | None:
    """A client's closed-loop success in its own conditions (``own-*`` or ``personal-own-*``), with its interval."""
    if f"{prefix}success-rate" not in evaluation:
        return None
    return evaluation[f"{prefix}success-rate"], success_text(evaluation, prefix)


def _charts(server_dir: Path) -> list[dict]:
    charts = []
    for metric, filename in {**CHARTS, **SIM_CHARTS}.items():
        path = server_dir / filename
        if path.is_file():
            charts.append({"title": f"{metric} per round", "data": base64.b64encode(path.read_bytes()).decode()})
    return charts


def _videos(run_dir: Path, best: dict | None, last: int) -> list[dict]:
    """The best and the latest round's rollout videos, linked by relative path (they stay beside it)."""
    rounds = {last: "latest round"} | ({best["round"]: "best round"} if best else {})  # one video if both
    videos = []
    for number, title in sorted(rounds.items()):
        src = f"server/videos/round_{number}.mp4"
        if (run_dir / src).is_file():
            videos.append({"title": f"Round {number} ({title})", "src": src})
    return videos


def render(run_dir: Path, history: dict, config: dict, best: dict | None, num_rounds: int) -> str:
    """The report's HTML for ``run_dir``, from its history (as ``metrics_history.json`` has it)."""
    rounds = [round_row(r) for r in history["rounds"]]
    last = rounds[-1]["round"] if rounds else 0
    ending = " (finished)." if last >= num_rounds else "; the run goes on or was stopped."
    status = f"Round {last} of {num_rounds}{ending}"
    best_path = run_dir / "models" / "best"
    columns = [{"key": k, "title": t} for k, t in ROUND_COLUMNS if any(r["cells"][k] is not None for r in rounds)]
    clients = client_rows(history)
    tasks, by_task = task_rows(history)
    return _TEMPLATE.render(
        name=run_dir.name,
        status=status,
        privacy=privacy_sentence(history, config),
        best=best,
        best_path=str(best_path),
        rollout=ROLLOUT.replace("POLICY", str(best_path)),
        round_columns=columns,
        rounds=rounds,
        tasks=tasks,
        task_rows=by_task,
        charts=_charts(run_dir / "server"),
        videos=_videos(run_dir, best, last),
        clients=clients,
        personal=any(c["personal_mse"] is not None for c in clients),
        outside_span=outside_span(history),
        personal_rollout=ROLLOUT.replace("POLICY", "clients/client_<i>/models/personal"),
        config=sorted(config.items()),
    )


def write_report(run_dir: Path, history: dict, config: dict, best: dict | None, num_rounds: int) -> Path:
    """Write ``report.html`` in ``run_dir`` atomically (a browser open on it never sees half a page)."""
    path = run_dir / REPORT_FILE
    write_text(path, render(run_dir, history, config, best, num_rounds))
    return path
