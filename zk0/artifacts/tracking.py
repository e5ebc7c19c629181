"""Optional Weights & Biases logging of each round's record (``use-wandb = true``).

Off by default. A missing ``wandb`` package or ``WANDB_API_KEY`` costs one warning,
never the run.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from loguru import logger

from zk0.config import RunConfig


@dataclass
class Tracker:
    """A W&B run, or nothing."""

    wandb_run: Any = None

    @classmethod
    def start(cls, run: RunConfig, run_dir: Path) -> Tracker:
        if not run.use_wandb:
            return cls()
        if not os.environ.get("WANDB_API_KEY"):
            logger.warning("use-wandb is set but WANDB_API_KEY is not; logging to W&B is off for this run.")
            return cls()
        try:
            import wandb
        except ImportError:
            logger.warning("use-wandb is set but the wandb package is not installed; logging to W&B is off.")
            return cls()
        return cls(wandb.init(project="zk0", name=run_dir.name, dir=str(run_dir), config=run.to_flat()))

    def log(self, server_round: int, record: dict) -> None:
        if self.wandb_run is None:
            return
        flat = {}
        for section in ("server-evaluate", "aggregate-train", "aggregate-evaluate"):
            flat.update({f"{section}/{k}": v for k, v in record.get(section, {}).items()})
        self.wandb_run.log(flat, step=server_round)

    def finish(self) -> None:
        if self.wandb_run is not None:
            self.wandb_run.finish()
