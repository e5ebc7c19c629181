"""Server-side (outer) optimisers: how the server steps from the averaged update.

Every choice is a Flower strategy of the FedAvg family, wrapped by
``zk0.federation.aggregation.ValidatingStrategy``: plain averaging (``fedavg``), Flower's ``FedAvgM``,
``FedAdam`` and ``FedYogi``, and outer Nesterov momentum (``nesterov``, DiLoCo's outer
optimiser), which Flower has not and zk0 implements here in the shape of Flower's ``FedAvgM``.

At equal samples a federation takes fewer sequential steps than pooled training (each round
averages the clients' steps from the same weights); an outer optimiser treats
``global - average`` as a gradient and takes a larger, smarter step with it. Its state
(momentum, Adam's moments) is what a resumed run must get back, so it is read and restored here
as named arrays (``optimiser_state`` / ``restore_state``) and kept next to each checkpoint.

Flower's ``FedAdam``/``FedYogi`` defaults (``eta = 0.1``, ``tau = 1e-3``) move every weight by
about 0.07 in round 1: far too much for a pretrained policy. zk0 sets ``tau`` below the size of a
fine-tuning update, so each weight moves by about ``server-lr`` per round, and defaults that to
1e-2 (1e-3 barely moved the study's model: docs/learning.md).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from flwr.app import Array, ArrayRecord, ConfigRecord, Message, MetricRecord
from flwr.serverapp import Grid
from flwr.serverapp.strategy import FedAdam, FedAvg, FedAvgM, FedYogi
from loguru import logger

from zk0.config import DEFAULT_SERVER_LR

ADAPTIVE_TAU = 1e-6  # FedAdam/FedYogi's epsilon: below a fine-tuning update's size, so the step is ~server-lr
# The arrays each optimiser carries from round to round (Flower's attribute names, and zk0's).
STATE = {"fedavg": (), "fedavgm": ("momentum_vector",), "nesterov": ("momentum",), "fedadam": ("m_t", "v_t")}
STATE["fedyogi"] = STATE["fedadam"]


class FedNesterov(FedAvg):
    """FedAvg with outer Nesterov momentum (Douillard et al., 2023, "DiLoCo").

    With the global model ``w``, the clients' weighted average ``a`` and the momentum buffer ``b``
    (zero at the start), each round takes ``g = w - a``, ``b = momentum * b + g`` and
    ``w = w - lr * (g + momentum * b)``: PyTorch's SGD with ``nesterov=True`` on the
    pseudo-gradient. With ``lr = 1`` and ``momentum = 0`` it is FedAvg.
    """

    def __init__(self, *, server_learning_rate: float = 1.0, server_momentum: float = 0.5, **kwargs) -> None:
        super().__init__(**kwargs)
        self.server_learning_rate = server_learning_rate
        self.server_momentum = server_momentum
        self.current_arrays: dict[str, np.ndarray] | None = None
        self.momentum: dict[str, np.ndarray] = {}

    def summary(self) -> None:
        logger.info(
            "Outer Nesterov momentum: server learning rate {}, momentum {}",
            self.server_learning_rate,
            self.server_momentum,
        )
        super().summary()

    def configure_train(
        self, server_round: int, arrays: ArrayRecord, config: ConfigRecord, grid: Grid
    ) -> Iterable[Message]:
        self.current_arrays = {name: array.numpy() for name, array in arrays.items()}
        return super().configure_train(server_round, arrays, config, grid)

    def aggregate_train(
        self, server_round: int, replies: Iterable[Message]
    ) -> tuple[ArrayRecord | None, MetricRecord | None]:
        average, metrics = super().aggregate_train(server_round, replies)
        if average is None:
            return average, metrics
        lr, momentum = self.server_learning_rate, self.server_momentum
        stepped = {}
        for name, current in self.current_arrays.items():
            gradient = current - average[name].numpy()
            buffer = momentum * self.momentum.get(name, np.zeros_like(gradient)) + gradient
            self.momentum[name] = buffer
            stepped[name] = Array(np.asarray(current - lr * (gradient + momentum * buffer), dtype=current.dtype))
        return ArrayRecord(stepped), metrics


def make_strategy(name: str, lr: float, momentum: float, **flower_kwargs) -> FedAvg:
    """The Flower strategy for ``server-optimiser = name`` (``lr`` 0: its default; ``momentum`` is
    FedAvgM's and Nesterov's; FedAdam and FedYogi keep Flower's beta_1 = 0.9, beta_2 = 0.99)."""
    lr = lr or DEFAULT_SERVER_LR[name]
    if name == "fedavg":
        return FedAvg(**flower_kwargs)
    if name == "fedavgm":
        return FedAvgM(server_learning_rate=lr, server_momentum=momentum, **flower_kwargs)
    if name == "nesterov":
        return FedNesterov(server_learning_rate=lr, server_momentum=momentum, **flower_kwargs)
    adaptive = {"fedadam": FedAdam, "fedyogi": FedYogi}[name]
    return adaptive(eta=lr, tau=ADAPTIVE_TAU, **flower_kwargs)


def optimiser_name(strategy: FedAvg) -> str:
    """Which ``server-optimiser`` built ``strategy``."""
    kinds = {FedNesterov: "nesterov", FedAvgM: "fedavgm", FedAdam: "fedadam", FedYogi: "fedyogi", FedAvg: "fedavg"}
    return kinds[type(strategy)]


def optimiser_state(strategy: FedAvg, names: list[str]) -> dict[str, np.ndarray]:
    """The arrays the optimiser carries into the next round, as ``<state>/<array name>``
    (``names``: the global model's array names, the order FedAvgM's list follows)."""
    state = {}
    for attribute in STATE[optimiser_name(strategy)]:
        value = getattr(strategy, attribute)
        if isinstance(value, list):  # FedAvgM keeps a list in the model's order
            value = dict(zip(names, value, strict=True))
        state |= {f"{attribute}/{name}": np.ascontiguousarray(array) for name, array in (value or {}).items()}
    return state


def restore_state(strategy: FedAvg, state: dict[str, np.ndarray], names: list[str], saved_by: str | None) -> None:
    """Give ``strategy`` back what ``optimiser_state`` read (a resumed run continues its momentum);
    ``saved_by`` is the optimiser that saved it, and another's state is not restored."""
    if saved_by is not None and saved_by != optimiser_name(strategy):
        logger.warning(
            "The checkpoint keeps server-optimiser={!r}'s state and this run uses {!r}, which starts afresh.",
            saved_by,
            optimiser_name(strategy),
        )
        return
    for attribute in STATE[optimiser_name(strategy)]:
        prefix = f"{attribute}/"
        arrays = {key.removeprefix(prefix): value for key, value in state.items() if key.startswith(prefix)}
        if not arrays:
            continue
        value = [arrays[name] for name in names] if attribute == "momentum_vector" else arrays
        setattr(strategy, attribute, value)
