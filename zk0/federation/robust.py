"""Robust aggregation: Flower's rules for combining updates when an owner may be hostile.

``update-clip`` bounds how large an update may be, not where it points: an owner whose update
is the others' negated, scaled to their median norm, passes it and pulls the average back by
up to a whole owner's share. The rules here limit what one owner can do to the combination
itself, each Flower's own Message-API strategy, used only for its ``aggregate_train``:

- ``median``: the coordinate-wise median (``FedMedian``; Yin et al. 2018);
- ``trimmed-mean``: per coordinate, the mean after dropping the ``trim-fraction`` largest and
  smallest values (``FedTrimmedAvg``);
- ``krum``: the one update closest to its ``n - f - 2`` nearest others (``Krum``; Blanchard et
  al. 2017), ``f`` = ``hostile-owners``;
- ``multi-krum``: the mean of the ``n - f`` updates Krum scores best (``MultiKrum``).

The server optimiser then steps from the combination as it steps from the mean
(``zk0.federation.aggregation``). Each rule costs something when nobody attacks: it discards information
the mean keeps (docs/privacy.md measures it).
"""

from __future__ import annotations

from flwr.app import ArrayRecord, Message
from flwr.serverapp.strategy import FedAvg, FedMedian, FedTrimmedAvg, Krum, MultiKrum
from loguru import logger

from zk0.config import RunConfig


def make_rule(run: RunConfig, weighted_by_key: str) -> FedAvg | None:
    """The Flower strategy whose ``aggregate_train`` combines the round's updates, or None for the
    weighted mean the server optimiser computes itself (``aggregation = "mean"``)."""
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


def combine(rule: FedAvg, server_round: int, replies: list[Message]) -> ArrayRecord | None:
    """The rule's combination of ``replies`` (their arrays are consumed: Flower's median and trimmed
    mean take them out of the messages). Multi-Krum averages all but the ``hostile-owners`` worst
    scored; Krum and Multi-Krum need more than ``2 f + 2`` updates to tell the hostile apart, and
    say so when a round has fewer."""
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
