"""Hostile owners for the benchmarks: ByzFL's attacks, substituted at the server.

ByzFL's standard attacks are functions of the honest owners' updates: ``sign-flipping`` sends
their mean negated, ``ipm`` (inner-product manipulation) twice their mean negated, ``alie`` ("a
little is enough") their mean plus 1.5 of their per-weight standard deviations, ``mimic`` a copy of
the first honest owner's, ``gaussian`` noise at their per-weight scale; every hostile owner sends
the same one. An attacker who sees every honest update is one no real owner can be, so the
benchmarks substitute the hostile owners' updates at the server, after Flower delivers them and
before zk0 checks, clips and combines them: a ServerApp that is zk0's own with its strategy
subclassed (``attacked_app``), stated as such in every table. ``negated`` is each hostile owner's
own update times ``factor`` (what zk0.bench.robust's ClientApp sends), substituted at the same
place so that 1 and 3 hostile owners are one mechanism.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

import torch
from flwr.app import Message
from loguru import logger

from zk0.data.registry import PROJECT_ROOT
from zk0.federation.aggregation import ValidatingStrategy
from zk0.federation.robust import flatten, moved
from zk0.federation.wire import CLIENT

ATTACKS = ("negated", "sign-flipping", "ipm", "alie", "mimic", "gaussian")


def attack_vector(attack: str, honest: torch.Tensor) -> torch.Tensor:
    """ByzFL's ``attack`` of the stacked honest updates (one row each)."""
    from byzfl import ALittleIsEnough, Gaussian, InnerProductManipulation, Mimic, SignFlipping

    made = {
        "sign-flipping": SignFlipping,
        "ipm": lambda: InnerProductManipulation(tau=2.0),
        "alie": lambda: ALittleIsEnough(tau=1.5),
        "mimic": lambda: Mimic(epsilon=0),
        "gaussian": lambda: Gaussian(mu=0.0, sigma=float(honest.std())),
    }
    return made[attack]()(honest).float()


def client_index(msg: Message) -> int:
    return int(msg.content[CLIENT]["index"])


class AttackedStrategy(ValidatingStrategy):
    """zk0's strategy, except that the updates of the clients in ``hostile`` are replaced by
    ``attack`` before they are checked (the benchmark's omniscient attacker; class attributes,
    set by the generated ServerApp module)."""

    attack: str = "negated"
    hostile: frozenset[int] = frozenset()
    factor: float = -2.9  # negated: what each hostile owner's own update is multiplied by

    def valid_updates(self, server_round: int, replies: Iterable[Message]) -> list[Message]:
        valid = super().valid_updates(server_round, replies)
        hostile = [msg for msg in valid if client_index(msg) in self.hostile]
        honest = [msg for msg in valid if client_index(msg) not in self.hostile]
        if not hostile or not honest:
            return valid
        key = self.inner.arrayrecord_key
        current = {name: array.numpy() for name, array in self.current.items()}
        with torch.random.fork_rng(devices=[]):  # gaussian draws: the same each round of a rerun
            torch.manual_seed(server_round)
            shared = None
            if self.attack != "negated":
                shared = attack_vector(self.attack, torch.stack([flatten(m.content[key], current) for m in honest]))
        for msg in hostile:
            own = flatten(msg.content[key], current)
            msg.content[key] = moved(current, self.factor * own if shared is None else shared)
        logger.info(
            "Round {}: the benchmark's attacker replaced the updates of client(s) {} with {} of the {} honest one(s).",
            server_round,
            sorted(client_index(m) for m in hostile),
            f"their own times {self.factor:g}" if shared is None else f"ByzFL's {self.attack}",
            len(honest),
        )
        return valid


ATTACKED_SERVER = '''"""zk0's ServerApp with the benchmark's attacker: clients {hostile} send {attack} (substituted at the server)."""

from zk0 import server_app
from zk0.bench.attacks import AttackedStrategy

AttackedStrategy.attack, AttackedStrategy.hostile, AttackedStrategy.factor = {attack!r}, frozenset({hostile!r}), {factor!r}
server_app.ValidatingStrategy = AttackedStrategy
app = server_app.app
'''


def attacked_app(folder: Path, attack: str, hostile: Iterable[int], factor: float = -2.9) -> Path:
    """A Flower app in ``folder``: zk0's ClientApp and run config, and zk0's ServerApp whose
    strategy replaces the ``hostile`` clients' updates with ``attack`` (for ``flwr run``)."""
    folder.mkdir(parents=True, exist_ok=True)
    pyproject = (PROJECT_ROOT / "pyproject.toml").read_text()
    pyproject = re.sub(r'serverapp = "zk0.server_app:app"', 'serverapp = "attacked_server:app"', pyproject)
    (folder / "pyproject.toml").write_text(pyproject.replace('name = "zk0"', 'name = "zk0-attacked"', 1))
    module = ATTACKED_SERVER.format(attack=attack, hostile=sorted(hostile), factor=factor)
    (folder / "attacked_server.py").write_text(module)
    return folder
