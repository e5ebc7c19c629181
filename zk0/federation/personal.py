"""A robot owner's personal model: the global model fine-tuned on the owner's own data, kept on the
owner's machine.

With ``personal-steps`` N, whenever a client evaluates the global model it also fine-tunes a copy
of it for N steps on its own training episodes (local fine-tuning of the federated model, the
strong baseline of Wang et al. 2019, "Federated Evaluation of On-device Personalization";
``personal-mu`` adds a proximal pull toward the global model, as Ditto's personal objective does,
Li et al. 2021), evaluates it on the same held-out episodes, and writes it as a lerobot policy
folder next to the client's log (``clients/client_<i>/models/personal``), normalised with the
owner's own statistics. In simulated conditions it also rolls both models out in the owner's own
set-up. The server only learns the metrics the client reports: the personal model never
travels, and the client's share of the federation (the weights it trains from, its optimizer,
its data order, its random state) continues exactly as if nothing had been fine-tuned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from zk0.artifacts.run_folder import PERSONAL, save_checkpoint
from zk0.config import RunConfig
from zk0.data.loaders import DatasetSplit, train_loader
from zk0.learning.closed_loop import ClosedLoop, summary
from zk0.learning.policy import PolicyBundle, rng_devices, set_trainable, snapshot
from zk0.learning.rates import mcnemar
from zk0.learning.training import LocalTrainer, evaluate
from zk0.sim.tasks import SIM_SPECS


@dataclass
class Personaliser:
    """The owner's fine-tuning: a trainer with its own loader and optimizer over the client's policy,
    and, for a simulated owner, the closed loop in its own conditions (both built once per run)."""

    run: RunConfig  # the client's (the trainer's own has the fine-tune's rate and length)
    eval_batches: DataLoader
    trainer: LocalTrainer
    closed_loop: ClosedLoop | None = field(default=None)

    def __call__(self, evaluated_round: int, client_dir: Path, global_metrics: dict) -> dict[str, float]:
        """Fine-tune the global model now in the policy, judge and keep it, and put the global model
        back; the personal model's metrics (``personal-*``), and in simulated conditions both
        models' success in this owner's own set-up on the same seeded episodes, with McNemar's
        p-value for their difference (``personal-own-p``)."""
        started = time.perf_counter()
        bundle, run = self.trainer.bundle, self.run
        global_weights = snapshot(bundle)
        metrics: dict[str, float] = {}
        with torch.random.fork_rng(devices=rng_devices(bundle)):
            if self.closed_loop:
                global_episodes = self.closed_loop.rollouts(bundle)
                metrics |= own_conditions(summary(global_episodes), "")
            self.trainer.optimizer.state.clear()  # each fine-tune starts afresh from the global model
            self.trainer.restore(evaluated_round * run.personal_steps, None)  # a data position of its own
            trained = self.trainer.fit(run.personal_steps, run.personal_mu, global_step=0)
            personal = evaluate(
                bundle, self.trainer.split, self.eval_batches, run.eval_batches, run.seed, run.max_skip_fraction
            )
            metrics |= {f"personal-{key}": personal[key] for key in ("action-mse", "policy-loss")}
            metrics["personal-train-loss"] = trained["train-loss"]
            if self.closed_loop:
                personal_episodes = self.closed_loop.rollouts(bundle)
                metrics |= own_conditions(summary(personal_episodes), "personal-")
                metrics["personal-own-p"] = mcnemar(
                    [e.success for e in personal_episodes], [e.success for e in global_episodes]
                )
            kept = {**global_metrics, **metrics}  # the global model's figures beside the personal one's
            save_checkpoint(bundle, client_dir, evaluated_round, {}, PERSONAL, kept, evaluated_by="evaluate")
        set_trainable(bundle, global_weights)
        metrics["personal-s"] = time.perf_counter() - started
        return metrics

    def close(self) -> None:
        if self.closed_loop:
            self.closed_loop.close()


def fine_tuner(run: RunConfig, bundle: PolicyBundle, split: DatasetSplit) -> LocalTrainer:
    """The owner's fine-tuning: ``personal-steps`` steps on the client's own training episodes at
    ``personal-lr`` (default a quarter of ``lr``), on a schedule of their own (warm-up and decay
    over those steps), with a loader of its own in the client's process."""
    personal_run = replace(
        run, lr=run.personal_peak_lr, local_steps=run.personal_steps, num_server_rounds=1, num_workers=0
    )
    return LocalTrainer(bundle, split, train_loader(split.train, personal_run, bundle.device), personal_run)


def build_personaliser(
    run: RunConfig, bundle: PolicyBundle, split: DatasetSplit, eval_batches: DataLoader
) -> Personaliser:
    """A client's personal model for this run: its fine-tuner, and its closed loop when simulated."""
    trainer = fine_tuner(run, bundle, split)
    closed_loop = None
    if run.sim_eval_episodes and split.entry.name in SIM_SPECS:
        height, width, _ = split.meta.features["observation.images.front"]["shape"]
        closed_loop = ClosedLoop(
            split.entry.name, run.sim_eval_episodes, run.seed, height, width, run.sim_episode_length
        )
    return Personaliser(run, eval_batches, trainer, closed_loop)


def own_conditions(rates: dict[str, float], prefix: str) -> dict[str, float]:
    """A closed-loop result as the owner's metrics: ``own-success-rate`` and its interval, prefixed."""
    keep = ("success-rate", "success-low", "success-high", "episodes")
    return {f"{prefix}own-{key}": rates[key] for key in keep}
