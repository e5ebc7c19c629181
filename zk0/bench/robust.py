"""Robust: one client sending an update 1000x the others' cannot wreck the federation (update-clip).

A bad client's update is finite and the right shape (broken normalisation, a bug, a scaled
update), so validation lets it through; ``update-clip`` bounds it by the others' median. This
benchmark runs, through ``flwr run`` on the synthetic clients:

- **without**: the honest clients alone (``--clients - 1`` of them);
- **clipped**: the same plus one client whose update is ``--factor`` times what it trained,
  with ``update-clip`` at its default;
- **unclipped**: the same with ``update-clip = 0``;

and prints each run's server action MSE per round, and clipped / without (the target: <= 1.10).
The bad client is a real ClientApp, zk0's own with its reply scaled (``scaled_client_app``).

    python -m zk0.bench robust [--rounds 8] [--local-steps 20] [--clients 4] [--factor 1000]
        [--output-dir outputs/bench-robust]
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from zk0.common.errors import OneSentenceParser, positive
from zk0.config import RunConfig
from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.simulation import run_federation

FAULTY_CLIENT = '''"""zk0's ClientApp, except that client {index} sends {factor} times the change it trained."""

from flwr.app import Message
from flwr.clientapp import ClientApp

from zk0 import client_app
from zk0.federation.wire import decode, encode

app = ClientApp()
app.evaluate()(client_app.evaluate)


@app.train()
def train(msg: Message, context) -> Message:
    reply = client_app.train(msg, context)
    if reply.has_error() or int(reply.content["client"]["index"]) != {index}:
        return reply
    wire = str(context.run_config["wire-dtype"])
    start, trained = decode(msg.content["arrays"], wire), decode(reply.content["arrays"], wire)
    scaled = {{name: start[name] + {factor} * (trained[name] - start[name]) for name in trained}}
    reply.content["arrays"] = encode(scaled, wire)
    return reply
'''


def scaled_client_app(folder: Path, index: int, factor: float) -> Path:
    """A Flower app in ``folder``: zk0's ServerApp and run config, and zk0's ClientApp with client
    ``index``'s update scaled by ``factor`` (a bad client, for ``flwr run``)."""
    folder.mkdir(parents=True, exist_ok=True)
    pyproject = (PROJECT_ROOT / "pyproject.toml").read_text()
    pyproject = re.sub(r'clientapp = "zk0.client_app:app"', 'clientapp = "faulty_client:app"', pyproject)
    (folder / "pyproject.toml").write_text(pyproject.replace('name = "zk0"', 'name = "zk0-faulty-client"', 1))
    (folder / "faulty_client.py").write_text(FAULTY_CLIENT.format(index=index, factor=factor))
    return folder


def server_mse(history: dict) -> list[float]:
    return [r["server-evaluate"]["action-mse"] for r in history["rounds"] if r.get("server-evaluate")]


def bad_scales(history: dict, bad: int) -> list[float]:
    """What the server scaled the bad client's update by in each round (none in the run without it)."""
    rounds = [r["clients"].get(str(bad), {}).get("train", {}) for r in history["rounds"][1:]]
    return [train["update-scale"] for train in rounds if "update-scale" in train]


def build_parser() -> OneSentenceParser:
    """The benchmark's command line (the docs' commands are checked against it)."""
    parser = OneSentenceParser(prog="python -m zk0.bench robust", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=positive(int), default=8)
    parser.add_argument("--local-steps", type=positive(int), default=20)
    parser.add_argument("--clients", type=positive(int), default=4, help="with the bad one (the last)")
    parser.add_argument("--factor", type=positive(float), default=1000.0)
    parser.add_argument("--lr", type=positive(float), default=8e-3)
    parser.add_argument("--output-dir", default="outputs/bench-robust")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.clients < 3:
        parser.error(f"--clients got {args.clients}; expected >= 3 (a bad client and two others to compare it with)")
    out = Path(args.output_dir).resolve()
    keys = (
        f"num-server-rounds={args.rounds} local-steps={args.local_steps} lr={args.lr} eval-batches=1000 "
        f"checkpoint-interval={args.rounds} proximal-mu=0.0"
    )
    bad = args.clients - 1
    faulty = scaled_client_app(out / "faulty-app", bad, args.factor)
    runs = {
        "without": (f"{keys} min-train-clients={bad}", bad, PROJECT_ROOT),
        "clipped": (f"{keys} min-train-clients={args.clients}", args.clients, faulty),
        "unclipped": (f"{keys} min-train-clients={args.clients} update-clip=0.0", args.clients, faulty),
    }
    results = {}
    for label, (config, clients, app) in runs.items():
        history = run_federation(config, clients, out / label, f"bench robust: {label}", app=app)
        if history is None:
            return 1
        results[label] = {"server-action-mse": server_mse(history), "bad-client-update-scale": bad_scales(history, bad)}
        print(f"{label:<10} server action MSE per round: {', '.join(f'{m:.4g}' for m in server_mse(history))}")
    ratio = results["clipped"]["server-action-mse"][-1] / results["without"]["server-action-mse"][-1]
    print(
        f"one client at {args.factor:g}x, update-clip={RunConfig.update_clip:g}: final server action MSE "
        f"{ratio:.3f}x the run without it (target <= 1.10); unclipped: "
        f"{results['unclipped']['server-action-mse'][-1] / results['without']['server-action-mse'][-1]:.3g}x"
    )
    path = out / "robust.json"
    path.write_text(json.dumps({"settings": vars(args), "results": results, "clipped-vs-without": ratio}, indent=2))
    print(f"figures: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
