"""Will a CPU simulation fit in the machine's memory? Checked before ``flwr run`` starts, as the disk is.

On a CPU, every simulated client holds its SmolVLA, its AdamW moments and its dataset in the host's
memory, in one of Ray's actor processes; the server holds the global model beside them. Ray runs as
many actors at once as the federation config's CPUs allow, and each actor keeps the clients it has
built. A full-size SmolVLA client holds about 3.7 GiB besides the 0.8 GiB every process pays for
Python, torch and lerobot (docs/performance.md, ``python -m zk0.bench memory --full-size``): four of
them and the server ran a 24 GiB machine out of memory, and Ray's monitor killed workers, with a
traceback each on the console.

``sized_federation`` sizes how many clients train at once (Ray's ``init-args-num-cpus``) to the
memory available now, beside the server, which holds each client's update, reply and its decoding
as well as the model (10.2 GB for a full-size round of four clients), or refuses in one sentence naming the key to change; ``room_for_another``
tells a simulated client whether it may build another owner's client beside those it keeps.
"""

from __future__ import annotations

from pathlib import Path

import psutil

from zk0.common.errors import Zk0Error
from zk0.config import RunConfig

GIB = 2**30
PROCESS_BYTES = int(0.85 * GIB)  # Python, torch and lerobot imported (docs/performance.md)
# A built client after its first steps, beyond its process's imports (docs/performance.md, batch 2-8):
# the policy, its processors, the dataset and AdamW's moments.
# ACT trains all of itself: 0.4 GiB tiny, 1.1 GiB at lerobot's default size on the 64 px videos
# (2026-12-06, `python -m zk0.bench memory --policy act [--full-size]`), more on larger frames;
# Diffusion Policy 0.38 GiB tiny, 3.7 GiB at lerobot's default (its 255 M-parameter U-Net).
SESSION_BYTES = {
    "smolvla": {"tiny": int(0.1 * GIB), "tiny-128": int(0.15 * GIB), "full-size": int(3.7 * GIB)},
    "act": {"tiny": int(0.6 * GIB), "tiny-128": int(0.6 * GIB), "full-size": int(1.5 * GIB)},
    "diffusion": {"tiny": int(0.6 * GIB), "tiny-128": int(0.6 * GIB), "full-size": int(4.0 * GIB)},
}
# What the server holds for each client of a round besides its own model: the update it sent, the
# reply and its fp32 decoding (measured: a full-size simulation of 4 clients, its server process
# 10.2 GB at the round's end, 2026-12-06).
EXCHANGE_BYTES = {
    "smolvla": {"tiny": int(0.01 * GIB), "tiny-128": int(0.01 * GIB), "full-size": int(1.25 * GIB)},
    "act": {"tiny": int(0.1 * GIB), "tiny-128": int(0.1 * GIB), "full-size": int(0.45 * GIB)},  # every weight travels
    "diffusion": {"tiny": int(0.15 * GIB), "tiny-128": int(0.15 * GIB), "full-size": int(2.3 * GIB)},  # as ACT's, per weight
}
# A checkpoint's weights, fp32, become about this many times their bytes once trained (full-size: 1.8 GB
# of weights, 3.7 GiB built and stepped: gradients and two moments of the trainable fifth, buffers),
# and the server holds about this share of them for each client of a round.
WEIGHTS_FACTOR = 2.2
EXCHANGE_FACTOR = 0.75
SHARE = 0.8  # of the memory available now: Ray's monitor kills workers at 95% of the machine's


class NotEnoughMemory(Zk0Error):
    """The simulation cannot fit in this machine's memory."""


def weights_bytes(model: str) -> int:
    """A local checkpoint folder's weights; 0 for anything else."""
    folder = Path(model).expanduser()
    return sum(p.stat().st_size for p in folder.glob("*.safetensors")) if folder.is_dir() else 0


def session_bytes(model: str, policy: str = "smolvla") -> int | None:
    """What one built client of ``model`` holds (an offline size of ``policy``, or a local
    checkpoint folder's weights scaled); None where it cannot be told before the model is fetched
    (a Hub id)."""
    if model in SESSION_BYTES[policy]:
        return SESSION_BYTES[policy][model]
    return int(WEIGHTS_FACTOR * weights_bytes(model)) or None


def server_bytes(model: str, clients: int, policy: str = "smolvla") -> int:
    """What a simulation's server process holds at a round's end with ``clients`` clients: its
    imports, the global model as a client holds one, and each client's exchange."""
    exchange = EXCHANGE_BYTES[policy].get(model) or int(EXCHANGE_FACTOR * weights_bytes(model))
    return PROCESS_BYTES + (session_bytes(model, policy) or 0) + clients * exchange


def gib(count: float) -> str:
    return f"{count / GIB:.1f} GiB"


def sized_federation(run: RunConfig, federation: dict, available: int | None = None) -> tuple[dict, str | None]:
    """``federation`` (a simulation's config: num-supernodes, client-resources-num-cpus, ...) with
    ``init-args-num-cpus`` lowered so that the clients that train at once fit beside the server in
    ``SHARE`` of the ``available`` memory (default: now), and a sentence saying so; unchanged, with
    None, where they fit, where the clients train on a GPU, or where the model's size is unknown.
    Raises ``NotEnoughMemory`` when not even one client fits."""
    session = session_bytes(run.model, run.policy)
    if session is None or float(federation.get("client-resources-num-gpus", 0.0)) > 0:
        return federation, None
    per_client = PROCESS_BYTES + session
    budget = SHARE * (psutil.virtual_memory().available if available is None else available)
    cpus_each = float(federation.get("client-resources-num-cpus", 1))
    cpus = int(federation.get("init-args-num-cpus", psutil.cpu_count() or 1))
    clients = int(federation.get("num-supernodes", 1))
    at_once = min(int(cpus // cpus_each), clients)
    server = server_bytes(run.model, clients, run.policy)
    fits = int((budget - server) // per_client)
    if fits < 1:
        raise NotEnoughMemory(
            f"model={run.model!r} needs about {gib(server)} for the server of {clients} simulated clients and "
            f"{gib(per_client)} for each client training, and this machine has {gib(budget / SHARE)} of memory "
            "available; free some, or choose a smaller model (model='tiny')."
        )
    if fits >= at_once:
        return federation, None
    sized = {**federation, "init-args-num-cpus": int(fits * cpus_each)}
    return sized, (
        f"model={run.model!r} needs about {gib(per_client)} a simulated client and {gib(budget / SHARE)} of "
        f"memory is available, so {fits} of the {clients} clients {'trains' if fits == 1 else 'train'} at a time "
        f"instead of {at_once}."
    )


def room_for_another(run: RunConfig, available: int | None = None) -> bool:
    """Whether this process may build one more client beside those it keeps: room for it and for
    one more that another simulated client process may be building at the same time. A process
    that keeps several owners' clients drops them first when memory is short."""
    session = session_bytes(run.model, run.policy)
    if session is None:
        return True
    return (psutil.virtual_memory().available if available is None else available) * SHARE >= 2 * session
