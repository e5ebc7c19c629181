"""Resume an interrupted federation from its last complete checkpoint.

A run folder holds everything the server needs: checkpoints are renamed into place only
once complete, so the highest ``models/checkpoint_round_<N>`` is the resume point; the
metric history keeps rounds up to N (a round after N that a crash interrupted is run
again, so every round appears once); the checkpoint's trainable weights become the global
model, its ``client_stats/`` the clients' statistics and its ``server_optimiser.safetensors``
the server optimiser's state (momentum, moments). Rounds continue from N + 1 and the
learning-rate schedule, a function of the global round, continues with them.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from flwr.app import ArrayRecord
from lerobot.datasets.io_utils import cast_stats_to_numpy
from safetensors import safe_open
from safetensors.torch import load_file

from zk0.artifacts.run_folder import ROUND_FILE, SERVER_STATE_FILE, checkpoints
from zk0.config import ConfigError
from zk0.learning import adapters
from zk0.learning.policy import PolicyBundle, get_trainable

CLIENT_STATS = re.compile(r"client_(\d+)_.*")


@dataclass
class ResumePoint:
    """The state of an interrupted run at its last complete checkpoint."""

    run_dir: Path
    round: int
    checkpoint: Path
    rounds: dict[int, dict]
    client_stats: dict[int, dict]
    best: dict | None  # {"round", "action-mse"} of the run's models/best, if it has one
    server_optimiser: str | None = None  # the optimiser whose state the checkpoint keeps (None: none kept)
    server_state: dict[str, np.ndarray] = field(default_factory=dict)

    def trainable(self, bundle: PolicyBundle) -> ArrayRecord:
        """The resume point's trainable tensors (``checkpoint_trainable``)."""
        return checkpoint_trainable(self.checkpoint, bundle)


def checkpoint_trainable(checkpoint: Path, bundle: PolicyBundle) -> ArrayRecord:
    """A checkpoint's trainable tensors, under the policy's parameter names (a LoRA run's
    adapters come from the checkpoint's ``adapter/``; its merged weights are for users)."""
    if adapters.is_adapted(bundle.policy):
        adapters.load_adapter(bundle.policy, checkpoint)
        return get_trainable(bundle)
    weights = load_file(checkpoint / "model.safetensors")
    missing = [n for n in bundle.trainable_names if n not in weights]
    if missing:
        raise ConfigError(f"Checkpoint {str(checkpoint)!r} lacks trainable tensors such as {missing[:2]}.")
    return ArrayRecord({name: weights[name].float() for name in bundle.trainable_names})


def find_resume_point(resume_from: str) -> ResumePoint:
    """Read the last complete checkpoint and the history up to it from a run folder."""
    run_dir = Path(resume_from).expanduser().resolve()
    if not (run_dir / "server").is_dir():
        raise ConfigError(
            f"Run-config key 'resume-from' got {resume_from!r}; expected a zk0 run folder (outputs/<run>)."
        )
    done = checkpoints(run_dir)
    if not done:
        raise ConfigError(f"Run folder {str(run_dir)!r} has no complete checkpoint to resume from.")
    last, checkpoint = done[-1]
    history_file = run_dir / "server" / "metrics_history.json"
    records = json.loads(history_file.read_text())["rounds"] if history_file.is_file() else []
    rounds = {r["round"]: r for r in records if r["round"] <= last}
    stats = {
        int(m.group(1)): cast_stats_to_numpy(json.loads(p.read_text()))
        for p in (checkpoint / "client_stats").glob("*.json")
        if (m := CLIENT_STATS.fullmatch(p.stem))
    }
    return ResumePoint(run_dir, last, checkpoint, rounds, stats, best_so_far(run_dir), *server_state(checkpoint))


def server_state(checkpoint: Path) -> tuple[str | None, dict[str, np.ndarray]]:
    """The server optimiser a checkpoint's state belongs to, and the state (checkpoints written
    before zk0 kept it have none: the optimiser then starts afresh)."""
    path = checkpoint / SERVER_STATE_FILE
    if not path.is_file():
        return None, {}
    with safe_open(path, framework="numpy") as state:
        return state.metadata()["server-optimiser"], {key: state.get_tensor(key) for key in state.keys()}


def best_so_far(run_dir: Path) -> dict | None:
    """The round ``models/best`` holds and its server action MSE. It may come from a round after the
    resume point (run again now); it is still the best model this run folder has seen."""
    info = run_dir / "models" / "best" / ROUND_FILE
    if not info.is_file():
        return None
    record = json.loads(info.read_text())
    return {"round": record["round"], "action-mse": record["server-evaluate"]["action-mse"]}
