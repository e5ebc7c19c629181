"""The public starting point: one policy pretrained centrally on the server's public demonstrations.

Every real federation starts from a model trained on public data, as smolvla_base was trained on
community datasets; privacy (record-level DP-SGD needs good features first) and trust (a server
that knows what a useful update looks like) both lean on it. ``zk0 pretrain`` trains one policy on
every registry entry with ``role = "public"`` (demonstrations the server recorded in set-ups of
its own, never an owner's: an entry has one role), a batch from each in turn, each prepared with
its own processors, as the study's centralised baseline trains (zk0.learning.training's
``PooledTrainer``). It writes a lerobot policy folder whose processors carry the public sets'
merged statistics; a federation starts from it with ``model='<folder>'``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from loguru import logger

from zk0.artifacts.run_folder import save_policy_folder
from zk0.common.errors import Zk0Error
from zk0.config import RunConfig
from zk0.data.registry import Registry, load_registry
from zk0.federation.client import ClientSession, build_client
from zk0.federation.stats import with_merged_stats
from zk0.learning.training import PooledTrainer


def public_sets(run: RunConfig) -> Registry:
    """The run's registry, refused in one sentence if it names no public demonstrations."""
    registry = load_registry(run.registry)
    if not registry.public:
        raise Zk0Error(
            f"Registry {run.registry or 'pyproject.toml'!r} has no public datasets to pretrain on; expected entries "
            'with role = "public", or public = <count> in [tool.zk0.owners] (kind "sim" or "sim-cube").'
        )
    return registry


def public_trainer(run: RunConfig, registry: Registry) -> tuple[list[ClientSession], PooledTrainer]:
    """Each public set opened as an owner's would be, and one trainer over them all: the first
    set's policy, a batch from each set in turn, each prepared with its own processors."""
    sessions = [build_client(run, e, registry.model_cameras(), index=i) for i, e in enumerate(registry.public)]
    return sessions, PooledTrainer.over(sessions[0].bundle, [s.trainer for s in sessions], run)


def pretrain(run: RunConfig, steps: int, out: Path) -> dict:
    """Train ``run``'s policy for ``steps`` steps on the registry's public sets and write it to ``out``
    (a new folder); what it trained on and how long it took."""
    registry = public_sets(run)
    if out.exists():
        raise Zk0Error(f"--out {str(out)!r} exists; expected a new folder, so that no model is overwritten.")
    out.parent.mkdir(parents=True, exist_ok=True)
    sessions, trainer = public_trainer(replace(run, local_steps=steps), registry)
    bundle = trainer.bundle
    started = time.perf_counter()
    metrics = trainer.fit(steps, mu=0.0, global_step=0)
    stats = {s.split.entry.name: s.bundle.stats for s in sessions}
    save_policy_folder(with_merged_stats(bundle, list(stats.values())), out, stats)
    logger.info("Pretrained {} steps on {} public set(s) into {}", steps, len(sessions), out)
    return {
        "public-sets": [s.split.entry.name for s in sessions],
        "samples-from": dict(trainer.samples_from),
        "train-loss": metrics["train-loss"],
        "wall-s": time.perf_counter() - started,
    }
