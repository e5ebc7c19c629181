"""Robust aggregation: Flower's and ByzFL's rules for combining updates when an owner may be hostile.

``update-clip`` bounds how large an update may be, not where it points: an owner whose update
is the others' negated, scaled to their median norm, passes it and pulls the average back by
up to a whole owner's share. The rules here limit what one owner can do to the combination
itself. Flower's, each its own Message-API strategy used only for its ``aggregate_train``:

- ``median``: the coordinate-wise median (``FedMedian``; Yin et al. 2018);
- ``trimmed-mean``: per coordinate, the mean after dropping the ``trim-fraction`` largest and
  smallest values (``FedTrimmedAvg``);
- ``krum``: the one update closest to its ``n - f - 2`` nearest others (``Krum``; Blanchard et
  al. 2017), ``f`` = ``hostile-owners``;
- ``multi-krum``: the mean of the ``n - f`` updates Krum scores best (``MultiKrum``).

ByzFL's (EPFL/INRIA's library of robust aggregators), on the updates flattened into one vector
each (the change every owner proposes to the global model), unweighted:

- ``geometric-median``: the point nearest to every update in summed distance (Pillutla et al.
  2022; Weiszfeld's iterations, ``GeometricMedian``);
- ``centered-clipping``: the centre moved by the mean of each update's difference to it, clipped
  to the updates' median distance from their coordinate-wise median; three times, from that
  median (Karimireddy et al. 2021, ``CenteredClipping``);
- ``mda``: the mean of the ``n - f`` updates of smallest diameter (El-Mhamdi et al. 2020);
- ``meamed``: per coordinate, the mean of the ``n - f`` values nearest the median (Xie et al. 2018);
- ``caf`` and ``smea``: the mean weighted (``caf``) or restricted (``smea``) to the updates
  whose spread along the largest direction of variance is least (Allouah et al. 2024);
- ``monna``: the mean of the ``n - f`` updates nearest to the server's own update on its public
  data, that one included (Farhadkhani et al. 2023; zk0.federation.trusted trains it).

``pre-aggregation`` puts one of ByzFL's pre-aggregators before any of these (or the mean):
``nnm`` replaces each update by the mean of its ``n - f`` nearest neighbours (Allouah et al.
2023: with it, a robust rule keeps its guarantee on owners whose data differ), ``arc`` clips
the ``2 f (n - f) / n`` largest updates to the next one's norm (Allouah et al. 2024).

The server optimiser then steps from the combination as it steps from the mean
(``zk0.federation.aggregation``). Each rule costs something when nobody attacks: it discards information
the mean keeps (docs/privacy.md measures it).
"""

from __future__ import annotations

import statistics
from collections.abc import Callable

import numpy as np
import torch
from flwr.app import Array, ArrayRecord, Message
from flwr.serverapp.strategy import FedAvg, FedMedian, FedTrimmedAvg, Krum, MultiKrum
from loguru import logger

from zk0.config import BYZFL_RULES, COUNTING_RULES, RunConfig

Trusted = Callable[[int, dict[str, np.ndarray]], torch.Tensor]  # (round, global model) -> the server's update
CENTERED_CLIPPING_ITERATIONS = 3  # from the coordinate-wise median, which is already near the honest updates


class ByzflRule:
    """One of ByzFL's aggregators, after its pre-aggregator if the run names one, on the round's
    updates flattened to one float32 vector each. A fresh aggregator every round, seeded by the
    round for those that draw (``caf``, ``smea``): a resumed run combines as the uninterrupted one."""

    def __init__(self, name: str, pre_aggregation: str, hostile: int, trusted: Trusted | None = None) -> None:
        self.name, self.pre_aggregation, self.hostile = name, pre_aggregation, hostile
        self.trusted = trusted  # monna: the server's own update each round (zk0.federation.trusted)

    def __str__(self) -> str:
        pre = f"{self.pre_aggregation} then " if self.pre_aggregation != "none" else ""
        return f"{pre}{self.name} (ByzFL, hostile-owners={self.hostile})"

    def fewest_updates(self) -> int:
        """The fewest updates with which the rule can outvote ``hostile-owners`` of them (more than
        twice as many, where the rule or its pre-aggregator counts them)."""
        counts = self.name in COUNTING_RULES or self.pre_aggregation != "none"
        return 2 * self.hostile + 1 if counts else 1

    def steps(self, updates: torch.Tensor) -> list[Callable[[torch.Tensor], torch.Tensor]]:
        """ByzFL's pre-aggregator (if any) and aggregator, configured for this round's ``updates``."""
        from byzfl import ARC, CAF, MDA, NNM, SMEA, CenteredClipping, GeometricMedian, Meamed, MoNNA

        f = self.hostile
        rules = {
            "geometric-median": lambda: GeometricMedian(),
            "centered-clipping": lambda: centred_clipping(CenteredClipping),
            "mda": lambda: MDA(f=f),
            "meamed": lambda: Meamed(f=f),
            "caf": lambda: CAF(f=f),
            "smea": lambda: SMEA(f=f),
            "monna": lambda: MoNNA(f=f, idx=len(updates) - 1),  # the trusted update is the last
        }
        pre = {"nnm": lambda: NNM(f=f), "arc": lambda: ARC(f=f)}.get(self.pre_aggregation)
        rule = rules[self.name]() if self.name != "mean" else (lambda vectors: vectors.mean(dim=0))
        return [pre(), rule] if pre else [rule]

    def combine(
        self, server_round: int, replies: list[Message], current: dict[str, np.ndarray], key: str
    ) -> ArrayRecord:
        """The global model moved by the rule's combination of the replies' updates (``key``: their arrays)."""
        updates = torch.stack([flatten(msg.content[key], current) for msg in replies])
        if self.name == "monna":
            updates = torch.cat([updates, self.trusted(server_round, current)[None]])
            self.name_the_farthest(server_round, replies, updates)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(server_round)
            combined = updates
            for step in self.steps(updates):
                combined = step(combined)
        return moved(current, combined)

    def name_the_farthest(self, server_round: int, replies: list[Message], updates: torch.Tensor) -> None:
        """Say which owners' updates lie farthest from the server's own: the ``hostile-owners`` that
        MoNNA leaves out of its mean (the rest, and the server's, are averaged)."""
        distances = torch.linalg.vector_norm(updates[:-1] - updates[-1], dim=1)
        order = torch.argsort(distances, descending=True).tolist()
        farthest, kept = order[: self.hostile], order[self.hostile :]
        if not farthest or not kept:
            return
        logger.info(
            "Round {}: left out the update(s) of client(s) {}, farthest from the server's own on its public data "
            "(distance {:.3g}; the others' at most {:.3g})",
            server_round,
            sorted(int(replies[i].content["client"]["index"]) for i in farthest),
            float(distances[farthest].min()),
            float(distances[kept].max()),
        )


def centred_clipping(kind: type) -> Callable[[torch.Tensor], torch.Tensor]:
    """ByzFL's ``CenteredClipping`` started from the updates' coordinate-wise median, with the
    clip at their median distance from it: without the history Karimireddy et al. start from (a
    resumed run would lose it), a start at zero needs a clip as large as the updates, which lets
    a hostile one pull a whole clip's share each iteration."""

    def clipped(updates: torch.Tensor) -> torch.Tensor:
        centre = torch.median(updates, dim=0).values
        tau = float(statistics.median(torch.linalg.vector_norm(updates - centre, dim=1).tolist()))
        rule = kind(L=CENTERED_CLIPPING_ITERATIONS, tau=tau)
        rule.m = centre  # ByzFL's constructor refuses any m (its type check can never pass); its call reads this
        return rule(updates)

    return clipped


def flatten(arrays: ArrayRecord, current: dict[str, np.ndarray]) -> torch.Tensor:
    """One owner's change to the global model as one float32 vector (arrays in ``current``'s order)."""
    return torch.cat(
        [torch.from_numpy(arrays[n].numpy().astype(np.float32) - start).ravel() for n, start in current.items()]
    )


def moved(current: dict[str, np.ndarray], update: torch.Tensor) -> ArrayRecord:
    """The global model plus a flattened update, each array in its own shape and dtype."""
    arrays, offset = {}, 0
    for name, start in current.items():
        change = update[offset : offset + start.size].numpy().reshape(start.shape)
        arrays[name] = Array(np.asarray(start + change, dtype=start.dtype))
        offset += start.size
    return ArrayRecord(arrays)


def make_rule(run: RunConfig, weighted_by_key: str, trusted: Trusted | None = None) -> FedAvg | ByzflRule | None:
    """What combines the round's updates in place of the weighted mean: a Flower strategy (its
    ``aggregate_train``), a ByzFL rule (``monna`` with the server's ``trusted`` update), or None for
    the weighted mean the server optimiser computes itself (``aggregation = "mean"`` with no
    pre-aggregation)."""
    if run.aggregation in BYZFL_RULES or run.pre_aggregation != "none":
        return ByzflRule(run.aggregation, run.pre_aggregation, run.hostile_owners, trusted)
    if run.aggregation == "median":
        return FedMedian(weighted_by_key=weighted_by_key)
    if run.aggregation == "trimmed-mean":
        return FedTrimmedAvg(beta=run.trim_fraction, weighted_by_key=weighted_by_key)
    if run.aggregation == "krum":
        return Krum(num_malicious_nodes=run.hostile_owners, weighted_by_key=weighted_by_key)
    if run.aggregation == "multi-krum":
        return MultiKrum(
            num_malicious_nodes=run.hostile_owners,
            num_nodes_to_select=0,  # set each round: the replies less the hostile owners
            weighted_by_key=weighted_by_key,
        )
    return None


def rule_name(rule: FedAvg | ByzflRule) -> str:
    """How the server's summary names the rule."""
    return str(rule) if isinstance(rule, ByzflRule) else f"{type(rule).__name__} (Flower)"


def combine(
    rule: FedAvg | ByzflRule, server_round: int, replies: list[Message], current: dict[str, np.ndarray], key: str
) -> ArrayRecord | None:
    """The rule's combination of ``replies`` (their arrays are consumed: Flower's median and trimmed
    mean take them out of the messages; ``key`` names them, ``current`` is the global model they
    change), or None when a ByzFL rule has too few updates to outvote
    ``hostile-owners`` (the round then keeps the global model, and says so). Multi-Krum averages all
    but the ``hostile-owners`` worst scored; Krum and Multi-Krum need more than ``2 f + 2`` updates
    to tell the hostile apart, and say so when a round has fewer."""
    if isinstance(rule, ByzflRule):
        if len(replies) < rule.fewest_updates():
            logger.warning(
                "Round {}: {} updates are too few for {} to outvote the hostile (it needs {}); the global model is kept.",
                server_round,
                len(replies),
                rule,
                rule.fewest_updates(),
            )
            return None
        return rule.combine(server_round, replies, current, key)
    if isinstance(rule, MultiKrum):
        hostile = rule.num_malicious_nodes
        if len(replies) <= 2 * hostile + 2:
            logger.warning(
                "Round {}: {} updates are too few for Krum to single out {} hostile owner(s) (it needs more than {}).",
                server_round,
                len(replies),
                hostile,
                2 * hostile + 2,
            )
        if not isinstance(rule, Krum):
            rule.num_nodes_to_select = max(1, len(replies) - hostile)
    arrays, _ = rule.aggregate_train(server_round, replies)
    return arrays
