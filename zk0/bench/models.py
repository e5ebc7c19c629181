"""The models the benchmarks compare, trained and judged the same way for each of them.

A federation through the real app (``flwr run``, simulated clients) and its history; on the same
clients, model, batch size and samples, centralised training (every client's batches pooled),
the equal-steps variant of it and each client alone (zk0.learning.training.PooledTrainer, the clients' own
trainers); and every model evaluated on every client's held-out episodes and on the server's set,
offline and (for simulated owners) in closed loop, with each set's own processors, as the
federation's clients and server evaluate. ``zk0.bench.learning``, ``lora``, ``study`` and
``sim_learning`` build on these; none of them imports another benchmark's pieces.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch

from zk0.artifacts.resume import find_resume_point
from zk0.artifacts.run_folder import checkpoints
from zk0.bench.stash import Stash
from zk0.common.errors import positive
from zk0.config import OFFLINE_MODELS, RunConfig
from zk0.data.assets import ensure_dataset
from zk0.data.loaders import eval_loader, open_evaluation, open_metadata
from zk0.data.registry import Registry, generated_entry
from zk0.deployment.simulation import run_federation
from zk0.federation.client import ClientSession, build_client
from zk0.federation.personal import fine_tuner
from zk0.learning.policy import build_policy, set_trainable, snapshot
from zk0.learning.training import PooledTrainer, evaluate
from zk0.sim.tasks import SIM_SPECS

EVAL_ALL = 1000  # eval-batches: every held-out batch of the synthetic datasets
# The closed-loop benchmarks judge a federation's model by its rollouts, not by its offline figures:
# their federations evaluate one server batch (the round-0 and last-round rows of its history stay)
# and ask no owner to evaluate, which was most of a small federation's time (20 of 31 s).
JUDGED_BY_ROLLOUTS = {"eval-batches": 1, "fraction-evaluate": 0.0}
SERVER = "server"  # the server's evaluation set, as a column of the matrices
NEW_OWNER = "new owner"  # the conditions of an owner who joins once the federation is trained
NEW_FROM_GLOBAL, NEW_ALONE = "new owner from global", "new owner alone"  # its two models
Weights = dict[str, torch.Tensor]


def federate(args, rounds: int, name: str, **keys) -> dict | None:
    """One federation of the learning check (``keys``: more run-config keys); its metric history."""
    settings = {
        "num-server-rounds": rounds,
        "local-steps": args.local_steps,
        "batch-size": args.batch_size,
        "lr": args.lr,
        "eval-batches": EVAL_ALL,
        "checkpoint-interval": rounds,
        "min-train-clients": args.clients,
        "wire-dtype": args.wire_dtype,
        **keys,
    }
    # Strings as TOML basic strings (JSON's escaping: a regex's backslashes reach the run config as
    # typed), booleans as TOML's true and false (JSON's spelling too).
    run_config = " ".join(f"{k}={json.dumps(v) if isinstance(v, str | bool) else v}" for k, v in settings.items())
    started = time.perf_counter()
    history = run_federation(run_config, args.clients, Path(args.output_dir).resolve() / name, f"bench: {name}")
    if history is not None:
        history.update({"wall-s": time.perf_counter() - started, "config": run_config})
    return history


def continuation(folder: Path) -> dict:
    """The run-config keys of a benchmark's federation in ``folder`` (its own): a checkpoint every
    round and, where a stopped benchmark left a run with a complete checkpoint, ``resume-from``
    the newest such run. zk0's resume ends with the model an uninterrupted run ends with
    (tests/test_federation.py), so a study stopped in round 15 of 20 loses at most a round, not
    hours. A run stopped before its first checkpoint holds nothing to keep and is removed."""
    stopped = []
    for run in sorted(run.parent for run in folder.glob("*/server")):
        if checkpoints(run):
            stopped.append(run)
        else:
            shutil.rmtree(run)
    return {"checkpoint-interval": 1, **({"resume-from": str(stopped[-1])} if stopped else {})}


def kept_federation(args, stash: Stash, clients: int, keys: dict, server_bundle) -> Weights:
    """A federation of ``clients`` through ``flwr run`` (``keys``: its run config beyond ``federate``'s)
    and its final global model, both kept in ``stash``: a stopped benchmark continues the federation
    (``continuation``), a finished one is taken from the folder."""
    if not stash.has("federation"):
        folder = stash.folder / "federation"
        sized = argparse.Namespace(**{**vars(args), "clients": clients})
        keys = {**keys, **continuation(folder)}
        history = federate(sized, args.rounds, str(folder.relative_to(Path(args.output_dir))), **keys)
        if history is None:
            raise SystemExit(1)
        stash.figures("federation", lambda: {"run-dir": history["run-dir"], "wall-s": history["wall-s"]})
    run_dir = stash.figures("federation", dict)["run-dir"]
    return stash.weights("global", lambda: find_resume_point(run_dir).trainable(server_bundle).to_torch_state_dict())


def add_sim_cube_recipe(parser, demos: int) -> None:
    """The closed-loop benchmarks' shared options, at the documented sim-cube recipe's values
    (docs/learning.md): ``demos`` demonstrations per owner, 20 rounds x 75 steps of ``tiny-128`` at
    1e-3, 300 steps of personal fine-tuning, 100 seeded episodes per set-up, two training seeds."""
    parser.add_argument("--seeds", type=int, nargs="+", default=[42, 43])
    parser.add_argument("--demos", type=positive(int), default=demos, help="demonstrations per owner")
    parser.add_argument("--rounds", type=positive(int), default=20)
    parser.add_argument("--local-steps", type=positive(int), default=75)
    parser.add_argument("--batch-size", type=positive(int), default=8)
    parser.add_argument("--model", choices=OFFLINE_MODELS, default="tiny-128")
    parser.add_argument("--lr", type=positive(float), default=1e-3)
    parser.add_argument("--personal-steps", type=positive(int), default=300)
    parser.add_argument("--sim-episodes", type=positive(int), default=100)
    parser.add_argument(
        "--episode-length",
        type=positive(int),
        default=RunConfig.sim_episode_length,
        help="steps before an episode ends unsolved (the run config's sim-episode-length)",
    )
    parser.add_argument("--wire-dtype", default="bfloat16", choices=["bfloat16", "float32"])


def server_rows(history: dict) -> list[dict]:
    """The server's evaluation of every evaluated round."""
    return [{"round": r["round"], **r["server-evaluate"]} for r in history["rounds"] if r.get("server-evaluate")]


def sent_bytes(history: dict) -> int:
    """Bytes one client sent in the last round (its update; the global model it got is the same size)."""
    last = history["rounds"][-1]["clients"].values()
    return max(int(c["train"]["update-bytes"]) for c in last if "update-bytes" in c.get("train", {}))


def generate(registry: Registry, demos: int, public_demos: int | None = None) -> None:
    """The setting's generated datasets (the non-IID and simulated ones are not in `zk0 assets`);
    all of them, as the server checks every client dataset of the registry before round 1. A
    simulated client records ``demos`` demonstrations, a simulated public set ``public_demos``
    (None: its default)."""
    for entry in registry.entries:
        if entry.synthetic:
            episodes = {"client": demos, "public": public_demos}.get(entry.role) if entry.name in SIM_SPECS else None
            ensure_dataset(entry.name, episodes=episodes)


def from_the_start(sessions: list[ClientSession]) -> None:
    """Each client's data order back at its first batch: a model then trains on the same batches
    whatever was trained before it, or kept from an earlier run (zk0.bench.stash)."""
    for session in sessions:
        session.trainer.restore(0, None)


def centralised(
    sessions: list[ClientSession], run: RunConfig, start: Weights, cameras: list[str], wide: bool = False
) -> tuple[Weights, dict[str, int]]:
    """One policy trained on every client's batches, its weights and the samples it took from each client.

    By default a batch from each client in turn, for as many steps as all clients take together.
    With ``wide`` (the equal-steps baseline), only the federation's sequential steps (rounds x local
    steps), each on a batch from every client together (batch = clients x batch): the same samples
    in a quarter of the steps, so its gap to the default is what fewer sequential steps cost, and
    the federation's gap to it is what federating costs beyond that."""
    clients = len(sessions)
    if wide:
        pooled_run = replace(run, batch_size=run.batch_size * clients)
    else:
        pooled_run = replace(run, local_steps=run.local_steps * clients)
    from_the_start(sessions)
    first = sessions[0]
    bundle = build_policy(pooled_run, first.split.meta, first.split.entry, cameras)
    set_trainable(bundle, start)
    trainer = PooledTrainer.over(bundle, [s.trainer for s in sessions], pooled_run, wide=wide)
    trainer.fit(pooled_run.total_steps, mu=0.0, global_step=0)
    return snapshot(bundle), dict(trainer.samples_from)


def local_only(session: ClientSession, run: RunConfig, start: Weights) -> Weights:
    """One client alone, for the steps it takes in the federation."""
    from_the_start([session])
    set_trainable(session.bundle, start)
    session.trainer.fit(run.total_steps, mu=0.0, global_step=0)
    return snapshot(session.bundle)


def fine_tuned(session: ClientSession, run: RunConfig, start: Weights) -> Weights:
    """``start`` fine-tuned on the client's own training episodes as a federation's client
    fine-tunes its personal model (zk0.federation.personal: ``personal-steps`` at ``personal-lr``)."""
    set_trainable(session.bundle, start)
    fine_tuner(run, session.bundle, session.split).fit(run.personal_steps, run.personal_mu, global_step=0)
    return snapshot(session.bundle)


def new_owner(
    args, run: RunConfig, cameras: list[str], index: int, federated: Weights, start: Weights, stash: Stash
) -> tuple[ClientSession, dict[str, Weights], Stash]:
    """An owner who joins once the federation is trained (``--new-owner``, ``--new-demos``
    demonstrations): its session, its two models, each ``--new-steps`` steps on its own episodes
    (the global model fine-tuned as an owner fine-tunes a personal model, at a quarter of ``--lr``;
    the starting model trained at ``--lr`` as an owner alone trains), and the stash its models and
    rollouts are kept in: a folder of the study's named for the new owner, its demonstrations and
    steps, so another new owner's figures are never taken for these."""
    ensure_dataset(args.new_owner, episodes=args.new_demos)
    own = replace(run, num_server_rounds=1, local_steps=args.new_steps, personal_steps=args.new_steps)
    session = build_client(own, generated_entry(args.new_owner), cameras, index)
    kept = Stash(stash.folder / "new-owner" / f"{args.new_owner}-{args.new_demos}-demos-{args.new_steps}-steps", {})
    trained = {
        NEW_FROM_GLOBAL: kept.weights("from global", lambda: fine_tuned(session, own, federated)),
        NEW_ALONE: kept.weights("alone", lambda: local_only(session, own, start)),
    }
    return session, trained, kept


def evaluation_sets(sessions: list[ClientSession], registry: Registry, run: RunConfig) -> dict:
    """Column name -> (bundle, split, loader): each client's held-out episodes with that client's own
    processors, and the server's evaluation set with the server's, as the federation evaluates."""
    columns = {f"client {s.index}": (s.bundle, s.split, s.eval_batches) for s in sessions}
    entry = registry.get(run.server_eval_dataset)
    meta = open_metadata(entry)
    bundle = build_policy(run, meta, entry, registry.model_cameras())
    split = open_evaluation(entry, meta, bundle.policy.config, run)
    columns[SERVER] = (bundle, split, eval_loader(split.evaluation, run))
    return columns


def evaluate_all(
    models: dict[str, Weights], columns: dict, run: RunConfig, stash: Stash | None = None
) -> dict[str, dict[str, dict]]:
    """Every model on every evaluation set: {model: {column: {action-mse, policy-loss}}} (each
    model's row kept in ``stash``, or taken from it)."""

    def row(weights: Weights) -> dict[str, dict]:
        figures = {}
        for column, (bundle, split, loader) in columns.items():
            set_trainable(bundle, weights)
            m = evaluate(bundle, split, loader, run.eval_batches, run.seed, run.max_skip_fraction)
            figures[column] = {"action-mse": m["action-mse"], "policy-loss": m["policy-loss"]}
        return figures

    if stash is None:
        return {label: row(weights) for label, weights in models.items()}
    return {label: stash.figures(f"offline/{label}", lambda w=weights: row(w)) for label, weights in models.items()}


def closed_loop_all(
    plan: dict[str, list[str]],
    models: dict[str, Weights],
    columns: dict,
    episodes: int,
    seed: int,
    say: Callable[[str], None],
    stash: Stash | None = None,
    conditions: dict[str, tuple[str, str]] | None = None,
    episode_length: int = RunConfig.sim_episode_length,
) -> dict:
    """Models' success in closed loop in evaluation sets' conditions (the server's span, and each
    client's own set-up), with that set's processors: ``plan`` names, for each column, the models to
    roll out there. ``conditions`` adds columns of other conditions (zk0.sim.tasks' names), each
    rolled out with an evaluation set's processors: column -> (evaluation set, conditions).
    {model: {column: rates}}, each with its interval and its per-episode ``outcomes`` (1 = success,
    in seed order: every model meets the same ``episodes`` episodes, seeded from ``seed``, so two
    can be compared pairwise; in a multi-task set's conditions, task by task, with the ``kinds``
    each outcome is of). Each rollout's figures are kept in
    ``stash`` as it finishes, or taken from it; a set whose rollouts are all kept builds no envs.
    Episodes end unsolved after ``episode_length`` steps (a length other than the default is kept
    apart in the stash)."""
    from zk0.learning.closed_loop import ClosedLoop, summary  # MuJoCo: only for the simulated setting

    def name(column: str, label: str) -> str:
        length = "" if episode_length == RunConfig.sim_episode_length else f"x{episode_length}"
        return f"rollouts-{episodes}{length}/{column}/{label}"

    matrix: dict[str, dict[str, dict]] = {label: {} for label in models}
    for column, labels in plan.items():
        processors, where = (conditions or {}).get(column, (column, None))
        bundle, split, _ = columns[processors]
        if stash is not None and all(stash.has(name(column, label)) for label in labels):
            for label in labels:
                matrix[label][column] = stash.figures(name(column, label), dict)
            say(f"every model rolled out in {column}'s conditions (kept from an earlier run)")
            continue
        height, width, _ = split.meta.features["observation.images.front"]["shape"]
        loop = ClosedLoop(where or split.entry.name, episodes, seed, height, width, episode_length)

        try:
            for label in labels:

                def rollout(weights: Weights = models[label], bundle=bundle, loop=loop) -> dict:
                    set_trainable(bundle, weights)
                    rolled = loop.rollouts(bundle)
                    kinds = [e.kind for e in rolled]  # a multi-task set's: which task each outcome is of
                    return {
                        **summary(rolled),
                        "outcomes": [int(e.success) for e in rolled],
                        **({"kinds": kinds} if len(set(kinds)) > 1 else {}),
                    }

                kept = stash.figures(name(column, label), rollout) if stash is not None else rollout()
                matrix[label][column] = kept
        finally:
            loop.close()
        say(f"every model rolled out in {column}'s conditions")
    return {label: row for label, row in matrix.items() if row}
