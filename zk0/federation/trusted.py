"""A trusted direction: the server's own update on its public demonstrations, each round.

The server cannot tell a hostile owner from an owner whose room differs by looking at one update
alone; it can compare every update with one it trusts. Each round the server trains the global
model for ``local-steps`` steps on the registry's ``role = "public"`` sets (a batch from each in
turn, as ``zk0 pretrain`` does) and hands its change to the model to ByzFL's MoNNA, which averages
the ``n - f`` updates nearest to it (``aggregation = "monna"``: Farhadkhani et al. 2023, with the
server as the trusted participant; FLTrust's cosine score is the same idea, and in neither
library). Only trainable parameters travel, so no normalisation statistics (running means and
variances, which FLTrust's reproductions found dominate a score) enter the distance.

Each round starts from the same place a rerun would: the public sets' data order at the round's
first step and a fresh optimizer, so a resumed run's trusted updates are the uninterrupted one's.
"""

from __future__ import annotations

import numpy as np
import torch
from loguru import logger

from zk0.config import RunConfig
from zk0.data.registry import Registry
from zk0.federation.pretraining import public_trainer
from zk0.learning.policy import set_trainable, snapshot


class TrustedDirection:
    """The server's update on the public sets from a round's global model (``update``)."""

    def __init__(self, run: RunConfig, registry: Registry) -> None:
        _, self.trainer = public_trainer(run, registry)
        self.sources, self.bundle = self.trainer.sources, self.trainer.bundle
        self.steps, self.seed = run.local_steps, run.seed
        logger.info("Trusted direction: {} local steps a round on {}", self.steps, [e.name for e in registry.public])

    def update(self, server_round: int, current: dict[str, np.ndarray]) -> torch.Tensor:
        """The change ``local-steps`` steps on the public sets make to ``current`` (the round's global
        model, in the order the owners' updates are flattened), as one float32 vector."""
        done = (server_round - 1) * self.steps  # the pooled steps every earlier round took
        for i, source in enumerate(self.sources):  # a batch from each in turn: source i took every n-th
            source.restore((done + len(self.sources) - 1 - i) // len(self.sources), None)
        self.trainer.batches_seen = done
        self.trainer.optimizer.state.clear()  # a fresh optimizer each round, as after a resume
        start = {name: torch.from_numpy(array.copy()) for name, array in current.items()}
        set_trainable(self.bundle, start)
        with torch.random.fork_rng(devices=[]):  # the flow-matching noise: the round's own, not the server's
            torch.manual_seed(self.seed + server_round)
            self.trainer.fit(self.steps, mu=0.0, global_step=done)
        trained = snapshot(self.bundle)
        return torch.cat([(trained[name] - start[name]).ravel() for name in current])
