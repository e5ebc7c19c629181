"""Record-level differential privacy on the owner's machine: DP-SGD with Opacus, per demonstration.

With ``dp = "record"`` the update an owner sends says little about any one of their
demonstrations, even to the server: the noise is added on the owner's machine, before the
update leaves it. The unit protected is a demonstration (an episode), not a frame: frames of one
episode show the same room, table and people, so a guarantee per frame would say little. Each
local step therefore:

- samples demonstrations, each independently with probability ``q = dp-batch / training
  demonstrations`` (every one with ``dp-batch = 0``; Opacus's ``UniformWithReplacementSampler``:
  the Poisson sampling its accountant assumes), and ``dp-frames`` frames uniformly from each one
  drawn, so a demonstration adds exactly one gradient to a step: the mean loss of its frames;
- computes each demonstration's gradient with a forward and backward of its own (a batch of its
  frames) through the policy's ``forward`` (the loss ``update_policy`` uses). Opacus's hooks
  cannot follow SmolVLA's in-place residual additions and ``torch.func.vmap`` stops at its
  ``.item()`` calls, so the per-demonstration gradients are built one at a time;
- with ``dp-train = "projections"`` (or ``"head"``) only SmolVLA's projections (state, action and
  time; or the action output alone) take these steps and the rest of the trainable weights keep
  the global model's values: the noise a step adds grows with the square root of the weights it
  touches (docs/privacy.md);
- hands those gradients to Opacus's ``DPOptimizer`` around the trainer's own AdamW: it clips each
  to ``dp-clip``, adds Gaussian noise of ``dp-noise-multiplier x dp-clip`` to their sum, divides
  by the expected batch size and steps; lerobot's scheduler follows as in ``update_policy``;
- is composed by Opacus's ``RDPAccountant`` (sampled Gaussian mechanism at ``q``).

The accountant's steps travel with the training state (``Context.state``, the state a resumed
run continues from), so an owner's epsilon covers every round they trained. A step that would
take it past ``dp-epsilon-budget`` is not taken: the round ends there, and a round with none left
is refused in one sentence. With ``dp-noise-multiplier = 0`` the noise is Opacus's
``get_noise_multiplier`` for the run's planned steps, so a client that trains every round ends
at the budget. The noise comes from PyTorch's generator seeded per round (a resumed run equals an
uninterrupted one); Opacus's ``secure_mode`` would draw it from a cryptographic source instead.
"""

from __future__ import annotations

import time
import zlib
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from lerobot.utils.logging_utils import MetricsTracker
from loguru import logger
from opacus.accountants import RDPAccountant
from opacus.accountants.utils import get_noise_multiplier
from opacus.optimizers import DPOptimizer
from opacus.utils.uniform_sampler import UniformWithReplacementSampler
from torch.utils.data import default_collate

from zk0.common.errors import Zk0Error
from zk0.config import DP_PARTS
from zk0.learning.training import LocalTrainer


class RecordBudgetSpent(Zk0Error):
    """This owner's demonstrations have spent ``dp-epsilon-budget``: it trains no more in this run."""


def demonstration_frames(dataset) -> list[np.ndarray]:
    """The frame indices (as the dataset is indexed) of each training demonstration."""
    episodes = dataset.meta.episodes
    to_relative = dataset.absolute_to_relative_idx
    frames = []
    for episode in dataset.episodes or range(dataset.meta.total_episodes):
        absolute = range(int(episodes["dataset_from_index"][episode]), int(episodes["dataset_to_index"][episode]))
        frames.append(np.array([to_relative[i] if to_relative is not None else i for i in absolute]))
    return frames


def demonstration_part(batch: dict, i: int, frames: int, size: int) -> dict:
    """The ``frames`` samples of demonstration ``i`` in a preprocessed batch of ``size`` samples."""
    return {
        key: value[i * frames : (i + 1) * frames]
        if isinstance(value, torch.Tensor | list) and len(value) == size
        else value
        for key, value in batch.items()
    }


def private_part(policy: torch.nn.Module, part: str) -> list[str]:
    """The trainable parameters ``dp-train = part`` trains privately: all, or those inside the
    modules ``DP_PARTS`` names."""
    modules = DP_PARTS[part]
    return [
        name
        for name, p in policy.named_parameters()
        if p.requires_grad and (modules is None or set(name.split(".")) & set(modules))
    ]


@dataclass
class PrivateTrainer(LocalTrainer):
    """A ``LocalTrainer`` whose steps are DP-SGD over the owner's demonstrations (module docstring)."""

    sample_rate: float = field(init=False)
    noise_multiplier: float = field(init=False)
    private_optimizer: DPOptimizer = field(init=False)
    private: list[str] = field(init=False)  # the parameters the steps train (dp-train)
    _others: list[torch.nn.Parameter] = field(init=False)  # the trainable ones they leave at the global model
    _frames: list[np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        self._frames = demonstration_frames(self.split.train)
        demonstrations = len(self._frames)
        self.sample_rate = min(1.0, self.run.dp_batch / demonstrations) if self.run.dp_batch else 1.0
        self.private = private_part(self.bundle.policy, self.run.dp_train)
        params = dict(self.bundle.policy.named_parameters())
        self._others = [params[name] for name in self.bundle.trainable_names if name not in self.private]
        if not self.private:
            raise Zk0Error(
                f"dp-train={self.run.dp_train!r} matches none of the policy's trainable weights; expected dp-train='all'."
            )
        self.noise_multiplier = self.run.dp_noise_multiplier or get_noise_multiplier(
            target_epsilon=self.run.dp_epsilon_budget,
            target_delta=self.run.dp_delta,
            sample_rate=self.sample_rate,
            steps=self.run.total_steps,
            accountant="rdp",
        )
        self.private_optimizer = DPOptimizer(
            self.optimizer,
            noise_multiplier=self.noise_multiplier,
            max_grad_norm=self.run.dp_clip,
            expected_batch_size=max(1, round(self.sample_rate * demonstrations)),
        )
        logger.info(
            "Record-level DP over {} demonstrations of {}: each drawn with probability {:.3g} a step ({} frame(s) "
            "each), gradients of {} ({} weights) clipped to {:g}, noise multiplier {:.3g} (Opacus)",
            demonstrations,
            self.dataset_name,
            self.sample_rate,
            self.run.dp_frames,
            self.run.dp_train,
            sum(self.bundle.policy.get_parameter(n).numel() for n in self.private),
            self.run.dp_clip,
            self.noise_multiplier,
        )

    @property
    def private_steps(self) -> int:
        """The DP-SGD steps this owner took in the run: one per draw (a draw whose frames failed to
        decode counts too, so the figure never falls short), restored with the data order."""
        return self.batches_seen

    def epsilon(self, extra_steps: int = 0) -> float:
        """The owner's epsilon at ``dp-delta`` after the steps taken (and ``extra_steps`` more):
        Opacus's RDP accountant over that many sampled Gaussian steps, all at one noise and rate."""
        steps = self.private_steps + extra_steps
        if not steps:
            return 0.0
        accountant = RDPAccountant()
        accountant.history = [(self.noise_multiplier, self.sample_rate, steps)]
        return float(accountant.get_epsilon(self.run.dp_delta))

    def _may_step(self, done: int) -> bool:
        if self.epsilon(1) <= self.run.dp_epsilon_budget:
            return True
        if done:
            logger.info("The next step would take epsilon past dp-epsilon-budget; this round ends after {}.", done)
            return False
        raise RecordBudgetSpent(
            f"its demonstrations have spent epsilon {self.epsilon():.3g} of dp-epsilon-budget="
            f"{self.run.dp_epsilon_budget:g} (delta {self.run.dp_delta:g}) in {self.private_steps} private steps, "
            "and one more would pass it; it trains no more in this run."
        )

    def _open_batches(self) -> None:
        """Nothing to open: each step draws its own demonstrations."""

    def _next_batch(self) -> dict | None:
        """``dp-frames`` frames of each demonstration the step's Poisson draw picked, in turn (None: it
        picked none). The draw is seeded by the run's seed, the dataset and the step, so a resumed
        run draws the same."""
        step = self.batches_seen
        self.batches_seen += 1
        seed = np.random.SeedSequence([self.run.seed, zlib.crc32(self.dataset_name.encode()), step])
        generator = torch.Generator().manual_seed(int(seed.generate_state(1, dtype=np.uint64)[0]))
        sampler = UniformWithReplacementSampler(
            num_samples=len(self._frames), sample_rate=self.sample_rate, generator=generator, steps=1
        )
        (drawn,) = list(sampler)
        if not drawn:
            return None
        frames = self.run.dp_frames
        picks = [
            self._frames[d][torch.randint(len(self._frames[d]), (frames,), generator=generator).numpy()] for d in drawn
        ]
        return default_collate([self.split.train[int(i)] for pick in picks for i in pick])

    def _prepare(self, batch: dict | None) -> dict | None:
        return None if batch is None else super()._prepare(batch)

    @contextmanager
    def _only_private(self):
        """The weights outside ``dp-train`` frozen for a step: Opacus's optimizer clips, noises and
        steps the parameters that require a gradient, and these keep the global model's values."""
        for p in self._others:
            p.requires_grad_(False)
            p.grad = None
        try:
            yield [self.bundle.policy.get_parameter(name) for name in self.private]
        finally:
            for p in self._others:
                p.requires_grad_(True)

    def _step(self, tracker: MetricsTracker, batch: dict | None) -> int:
        """A DP-SGD step: each demonstration's gradient, Opacus's clip, noise and AdamW step, then the schedule."""
        started = time.perf_counter()
        policy = self.bundle.policy
        policy.train()
        samples = 0 if batch is None else len(batch["action"])
        size = samples // self.run.dp_frames  # demonstrations drawn
        losses = []
        with self._only_private() as params:
            per_demo: list[list[torch.Tensor]] = [[] for _ in params]
            for i in range(size):
                for p in params:
                    p.grad = None
                with self.accelerator.autocast():
                    loss, _ = policy.forward(demonstration_part(batch, i, self.run.dp_frames, samples))
                loss.backward()
                losses.append(float(loss.detach()))
                for grads, p in zip(per_demo, params, strict=True):
                    grads.append(torch.zeros_like(p) if p.grad is None else p.grad.detach().clone())
            for grads, p in zip(per_demo, params, strict=True):
                p.grad = None
                p.grad_sample = torch.stack(grads) if grads else torch.zeros((0, *p.shape), device=p.device)
            norms = (
                torch.stack([p.grad_sample.reshape(size, -1).norm(dim=1) for p in params]).norm(dim=0) if size else None
            )
            self.private_optimizer.step()
            self.private_optimizer.zero_grad(set_to_none=True)
        if self.scheduler is not None:
            self.scheduler.step()
        tracker.loss = sum(losses) / size if size else 0.0
        tracker.grad_norm = float(norms.mean()) if norms is not None else 0.0
        tracker.lr = self.optimizer.param_groups[0]["lr"]
        tracker.update_s = time.perf_counter() - started
        return samples

    def fit(self, steps: int, mu: float, global_step: int, budget_s: float = 0.0) -> dict[str, float]:
        metrics = super().fit(steps, mu, global_step, budget_s)
        epsilon = self.epsilon()
        logger.info(
            "Privacy spent by {}'s demonstrations: epsilon {:.3f} at delta {:g} after {} private steps (Opacus RDP; "
            "dp-epsilon-budget={:g})",
            self.dataset_name,
            epsilon,
            self.run.dp_delta,
            self.private_steps,
            self.run.dp_epsilon_budget,
        )
        return metrics | {"record-epsilon": epsilon, "noise-multiplier": self.noise_multiplier}
