"""Owner-level differential privacy on the server: Flower's mechanism and Flower's accountant.

With ``dp = "owner"`` the model the federation releases after each round reveals little about
whether any one owner took part: each owner's update is clipped to ``dp-clip`` (L2, over every
trainable weight) and Gaussian noise of ``dp-noise-multiplier x dp-clip`` is added to the sum,
which is then divided by the updates averaged (DP-FedAvg, McMahan et al. 2018). The clipping,
averaging and noise are Flower's ``DifferentialPrivacyServerSideFixedClipping`` around a plain
``FedAvg`` with equal weights; the privacy spent is Flower's ``RdpAccountant`` (Google's
``dp-accounting``); the noise that spends the budget over the planned rounds is found by
``dp-accounting``'s own calibration. zk0 adds three things the wrapper leaves to its caller:

- The noise matches the updates actually averaged. Flower fixes its divisor when the strategy
  is built and only warns when fewer replies arrive, and zk0's deadlines and refusals make that
  normal: here the divisor is set to the round's usable updates before every release, so the
  sum always carries noise of ``dp-noise-multiplier x dp-clip``.
- The server optimiser steps from the noisy average (``zk0.federation.aggregation``): post-processing,
  which spends nothing more. (Flower's wrapper around Nesterov would noise the stepped model,
  whose sensitivity is the step's, not the average's.)
- No amplification by sampling is claimed: Flower samples among the SuperNodes connected at
  that moment, not from a fixed population with a known rate, so each round costs the full
  Gaussian mechanism's epsilon whichever owners were sampled.

The accountant's state travels in every round's JSON, so a resumed run continues its epsilon,
and a run stops (``PrivacyBudgetSpent``) after the last round whose release fits the budget.
"""

from __future__ import annotations

import dp_accounting
from flwr.app import ArrayRecord, Message
from flwr.serverapp import GaussianPrivacyEvent, NeighboringRelation, PrivacyConfig, RdpAccountant, SamplingMethod
from flwr.serverapp.strategy import DifferentialPrivacyServerSideFixedClipping, FedAvg
from loguru import logger

from zk0.common.errors import Zk0Error
from zk0.config import ConfigError, RunConfig

EQUAL_WEIGHT = "dp-weight"  # the metric the mechanism's FedAvg weights by: 1 for every owner


class PrivacyBudgetSpent(Zk0Error):
    """The next release would take epsilon past ``dp-epsilon-budget``: the run ends here."""


def calibrated_noise(epsilon: float, delta: float, releases: int) -> float:
    """The smallest noise multiplier whose ``releases`` Gaussian releases spend at most ``epsilon``
    at ``delta`` under RDP accounting (``dp-accounting``'s calibration, no sampling amplification)."""

    def event(noise: float) -> dp_accounting.DpEvent:
        return dp_accounting.SelfComposedDpEvent(dp_accounting.GaussianDpEvent(noise), releases)

    return float(
        dp_accounting.calibrate_dp_mechanism(
            dp_accounting.rdp.RdpAccountant,
            event,
            epsilon,
            delta,
            dp_accounting.LowerEndpointAndGuess(1e-3, 1.0),
            tol=1e-4,
        )
    )


class OwnerLevelDP:
    """Clip, average and noise a round's updates with Flower's mechanism; account each release."""

    def __init__(self, run: RunConfig, population: int, state: dict | None = None):
        self.clip = run.dp_clip
        self.budget = run.dp_epsilon_budget
        self.population = population  # the registry's owners: the events' population (no amplification)
        self.noise_multiplier = run.dp_noise_multiplier or calibrated_noise(
            run.dp_epsilon_budget, run.dp_delta, run.num_server_rounds
        )
        averager = FedAvg(weighted_by_key=EQUAL_WEIGHT)
        self.mechanism = DifferentialPrivacyServerSideFixedClipping(averager, self.noise_multiplier, self.clip, 1)
        config = PrivacyConfig(
            target_delta=run.dp_delta,
            population_size=population,
            neighboring_relation=NeighboringRelation.ADD_OR_REMOVE_ONE,
            sampling_method=SamplingMethod.NO_AMPLIFICATION,
        )  # the budget is checked here, not kept in the config: a resumed run may raise it
        self.accountant = RdpAccountant(config)
        if state:
            try:
                self.accountant.load_state_dict(state)
            except ValueError as err:
                raise ConfigError(
                    f"The resumed run's privacy accounting cannot continue ({err}); resume with the dp-delta it "
                    "started with, or start a new run."
                ) from None
        if self.would_exceed(1):
            raise ConfigError(
                f"Run-config key 'dp-noise-multiplier' = {self.noise_multiplier:g} spends more than "
                f"dp-epsilon-budget={self.budget:g} in a single round (epsilon "
                f"{self.epsilon_after(1):.3g} at dp-delta={run.dp_delta:g}); expected a larger noise multiplier "
                "(0 picks the least that fits the budget) or a larger budget."
                if not self.accountant.num_releases
                else f"The resumed run has spent epsilon {self.spent()['epsilon']:.3g} of dp-epsilon-budget="
                f"{self.budget:g} and one more round would pass it; raise dp-epsilon-budget to train on."
            )

    def _event(self, sample_size: int) -> GaussianPrivacyEvent:
        return GaussianPrivacyEvent(self.noise_multiplier, min(max(sample_size, 1), self.population), self.population)

    def would_exceed(self, releases: int = 1) -> bool:
        """Whether ``releases`` more rounds would take epsilon past the budget."""
        return self.accountant.would_exceed(self._event(self.population), max_epsilon=self.budget, count=releases)

    def epsilon_after(self, releases: int) -> float:
        """Epsilon once ``releases`` more rounds are released (the accountant is left as it is)."""
        projected = RdpAccountant(self.accountant.config)
        projected.load_state_dict(self.accountant.state_dict())
        projected.compose(self._event(self.population), releases)
        return projected.get_privacy_spent().epsilon

    def release(self, server_round: int, replies: list[Message], current: ArrayRecord) -> ArrayRecord:
        """The clipped, averaged and noised update of ``replies`` (decoded, valid) from the global
        model ``current``: Flower's mechanism with its divisor set to the updates averaged."""
        for msg in replies:
            (metrics,) = msg.content.metric_records.values()
            metrics[EQUAL_WEIGHT] = 1.0
            arrays = msg.content[self.mechanism.strategy.arrayrecord_key]  # Flower clips by position: same order
            msg.content[self.mechanism.strategy.arrayrecord_key] = ArrayRecord({n: arrays[n] for n in current})
        self.mechanism.num_sampled_clients = len(replies)
        self.mechanism.current_arrays = current
        arrays, _ = self.mechanism.aggregate_train(server_round, replies)
        self.accountant.compose(self._event(len(replies)))
        spent = self.spent()
        logger.info(
            "Round {}: {} updates clipped to {:g}, averaged, noised (std {:.3g}); privacy spent: epsilon {:.3f} at "
            "delta {:g}",
            server_round,
            len(replies),
            self.clip,
            self.noise_multiplier * self.clip / len(replies),
            spent["epsilon"],
            spent["delta"],
        )
        return arrays

    def spent(self) -> dict:
        """Epsilon so far at the run's delta, the releases counted, the mechanism, and the accountant's
        state (what a resumed run continues from)."""
        spent = self.accountant.get_privacy_spent()
        return {
            "kind": "owner",
            "epsilon": spent.epsilon,
            "delta": spent.delta,
            "releases": spent.num_releases,
            "noise-multiplier": self.noise_multiplier,
            "clip": self.clip,
            "budget": self.budget,
            "accountant": self.accountant.state_dict(),
        }
