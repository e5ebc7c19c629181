"""Trainable weights on the wire: packed into one array, fp32 or bf16 as raw 16-bit patterns.

Flower's ``ArrayRecord`` goes through NumPy, which has no bfloat16, so bf16 travels as the
tensor's bit pattern viewed as int16 and is decoded back to fp32 on arrival. Both ends keep
fp32 master weights: the server averages decoded fp32 values and sends the average rounded to
bf16; a client loads that into its fp32 parameters. bf16 halves the bytes of every exchange.

Every tensor is packed into one array, with a manifest of names and shapes beside it: Flower
sends each array of a record as objects of its own, pulled one request at a time at every hop
(SuperLink, SuperNode, ClientApp), so a message of a few hundred tensors cost as many round
trips per hop; packed, it costs one per 5 MB chunk. The server decodes updates into one array
per tensor before it validates and averages them.
"""

from __future__ import annotations

import json

import numpy as np
import torch
from flwr.app import ArrayRecord

from zk0.common.errors import Zk0Error

# Names both ends use for the evaluation that rides on a train message (zk0.federation.aggregation):
EVALUATE_ROUND = "evaluate-round"  # train config: evaluate the received model (that round's) first
EVALUATION = "evaluation"  # train reply: a ConfigRecord with that evaluation's metrics, or its "error"
CLIENT = "client"  # every reply: a ConfigRecord naming the client ({"index": i, "dataset": name})
KEEP_STATE = "keep-state"  # train config: a checkpoint round, so the client keeps its training state (zk0.learning.client_state)
SHAPE = "shape:"  # config: the global model's state/action sizes, e.g. "shape:action" = [6]


PACKED = "zk0:packed"  # every tensor's values, one after another, in the wire dtype
MANIFEST = "zk0:manifest"  # UTF-8 JSON [[name, shape], ...]: how to cut PACKED back into tensors


def encode(tensors: dict[str, torch.Tensor], wire_dtype: str) -> ArrayRecord:
    """fp32 tensors -> an ArrayRecord of one array in ``wire_dtype`` and its manifest."""
    dtype = torch.float32 if wire_dtype == "float32" else torch.bfloat16
    packed = torch.empty(sum(t.numel() for t in tensors.values()), dtype=dtype)
    offset = 0
    for tensor in tensors.values():  # converted as copied: one pass over the weights, not two
        packed[offset : offset + tensor.numel()].copy_(tensor.detach().reshape(-1))
        offset += tensor.numel()
    if dtype == torch.bfloat16:
        packed = packed.view(torch.int16)
    manifest = json.dumps([[name, list(t.shape)] for name, t in tensors.items()]).encode()
    return ArrayRecord({PACKED: packed, MANIFEST: torch.frombuffer(bytearray(manifest), dtype=torch.uint8)})


def decode(arrays: ArrayRecord, wire_dtype: str) -> dict[str, torch.Tensor]:
    """An ArrayRecord from ``encode`` -> fp32 tensors (one sentence if it is not what ``encode`` sends)."""
    expected = "int16" if wire_dtype == "bfloat16" else "float32"
    if set(arrays) != {PACKED, MANIFEST}:
        raise Zk0Error(f"The weights arrived as arrays {sorted(arrays)[:3]}; zk0 sends {PACKED!r} and {MANIFEST!r}.")
    if arrays[PACKED].dtype != expected:
        raise Zk0Error(f"The weights arrived as {arrays[PACKED].dtype}; wire-dtype={wire_dtype} sends {expected}.")
    manifest = json.loads(bytes(arrays[MANIFEST].numpy()))
    packed = torch.from_numpy(arrays[PACKED].numpy())
    if wire_dtype == "bfloat16":
        packed = packed.view(torch.bfloat16).float()
    sizes = [int(np.prod(shape)) for _, shape in manifest]
    if sum(sizes) != packed.numel():
        raise Zk0Error(f"The weights arrived with {packed.numel()} values; their manifest describes {sum(sizes)}.")
    pieces = torch.split(packed, sizes)
    return {name: piece.view(shape) for (name, shape), piece in zip(manifest, pieces, strict=True)}
