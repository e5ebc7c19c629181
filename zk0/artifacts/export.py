"""``zk0 export``: a run's policy as a lerobot folder normalised for one robot owner.

A checkpoint's processors carry the statistics merged over every owner, which suit no one arm
exactly; ``client_stats/`` beside them keeps each owner's own. An owner who runs the global
model on their robot wants it normalised as their client trained it, and an owner with a
personal model (``personal-steps``) wants that one, which is already normalised for them.
Either way the result is a plain lerobot policy folder that ``lerobot-rollout --policy.path``
loads, written to a new folder only.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from lerobot.datasets.io_utils import cast_stats_to_numpy
from lerobot.processor import PolicyProcessorPipeline

from zk0.artifacts.resume import CLIENT_STATS
from zk0.artifacts.run_folder import PERSONAL, SERVER_STATE_FILE, checkpoints, client_dir
from zk0.common.errors import Zk0Error

# The processor steps whose statistics decide how observations and actions are scaled.
NORMALISING_STEPS = (
    ("policy_preprocessor", "normalizer_processor"),
    ("policy_postprocessor", "unnormalizer_processor"),
)


def export_policy(
    run_dir: Path, client: int, out: Path, personal: bool = False, server_round: int | None = None
) -> Path:
    """Write owner ``client``'s policy from ``run_dir`` to the new folder ``out``: the global model
    of ``server_round`` (default: the last checkpoint) with that owner's statistics in its
    processors, or (``personal``) the owner's personal model as its client kept it."""
    if out.exists() and any(out.iterdir()):
        raise Zk0Error(f"--out {str(out)!r} already holds files; expected a new or empty folder.")
    if not (run_dir / "server").is_dir() and not (run_dir / "clients").is_dir():
        raise Zk0Error(f"Run folder {str(run_dir)!r} is not a zk0 run (no server/ or clients/ in it).")
    source = personal_model(run_dir, client) if personal else checkpoint(run_dir, server_round)
    stats = None if personal else owner_stats(source, client)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.with_name(f".{out.name}.partial")  # renamed into place whole: no half-written policy
    shutil.rmtree(staging, ignore_errors=True)
    try:
        shutil.copytree(source, staging, ignore=shutil.ignore_patterns("client_stats", SERVER_STATE_FILE))
        for config, step in NORMALISING_STEPS if stats is not None else ():
            pipeline = PolicyProcessorPipeline.from_pretrained(
                staging, f"{config}.json", overrides={step: {"stats": stats}}
            )
            pipeline.save_pretrained(staging)
        if out.exists():
            out.rmdir()
        staging.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out


def checkpoint(run_dir: Path, server_round: int | None) -> Path:
    """The run's checkpoint of ``server_round`` (None: its last), or one sentence naming those it has."""
    done = dict(checkpoints(run_dir))
    if not done:
        raise Zk0Error(f"Run folder {str(run_dir)!r} has no complete checkpoint yet.")
    if server_round is None:
        return done[max(done)]
    if server_round not in done:
        raise Zk0Error(f"--round got {server_round}; this run has checkpoints of rounds {sorted(done)}.")
    return done[server_round]


def owner_stats(checkpoint_dir: Path, client: int) -> dict:
    """Client ``client``'s own statistics, kept in the checkpoint's ``client_stats/``."""
    kept = {
        int(m.group(1)): p
        for p in (checkpoint_dir / "client_stats").glob("*.json")
        if (m := CLIENT_STATS.fullmatch(p.stem))
    }
    if client not in kept:
        if not kept:
            raise Zk0Error(
                f"Checkpoint {str(checkpoint_dir)!r} keeps no owner's statistics (a run with dp on keeps them on the "
                "owners' machines); export the personal model (--personal) on the owner's machine instead."
            )
        raise Zk0Error(f"--client got {client}; this checkpoint keeps the statistics of clients {sorted(kept)}.")
    return cast_stats_to_numpy(json.loads(kept[client].read_text()))


def personal_model(run_dir: Path, client: int) -> Path:
    """Client ``client``'s personal model in this run folder, or the sentence saying how to get one."""
    folder = client_dir(run_dir, client) / "models" / PERSONAL
    if not (folder / "model.safetensors").is_file():
        raise Zk0Error(
            f"Client {client} has no personal model in {str(run_dir)!r}; it is written on the owner's machine "
            "by a run with personal-steps > 0."
        )
    return folder
