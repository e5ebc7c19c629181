"""Trainable weights on the wire: fp32, or bf16 as raw 16-bit patterns.

Flower's ``ArrayRecord`` goes through NumPy, which has no bfloat16, so bf16 travels as the
tensor's bit pattern viewed as int16 and is decoded back to fp32 on arrival. Both ends keep
fp32 master weights: the server averages decoded fp32 values and sends the average rounded to
bf16; a client loads that into its fp32 parameters. bf16 halves the bytes of every exchange.
"""

from __future__ import annotations

import torch
from flwr.app import ArrayRecord

from zk0.errors import Zk0Error

# Names both ends use for the evaluation that rides on a train message (zk0.aggregation):
EVALUATE_ROUND = "evaluate-round"  # train config: evaluate the received model (that round's) first
EVALUATION = "evaluation"  # train reply: a ConfigRecord with that evaluation's metrics, or its "error"
CLIENT = "client"  # every reply: a ConfigRecord naming the client ({"index": i, "dataset": name})
KEEP_STATE = "keep-state"  # train config: a checkpoint round, so the client keeps its training state (zk0.client_state)
SHAPE = "shape:"  # config: the global model's state/action sizes, e.g. "shape:action" = [6]


def encode(tensors: dict[str, torch.Tensor], wire_dtype: str) -> ArrayRecord:
    """fp32 tensors -> an ArrayRecord in ``wire_dtype``."""
    if wire_dtype == "float32":
        return ArrayRecord({name: t.detach().to("cpu", torch.float32) for name, t in tensors.items()})
    return ArrayRecord({name: t.detach().to("cpu", torch.bfloat16).view(torch.int16) for name, t in tensors.items()})


def decode(arrays: ArrayRecord, wire_dtype: str) -> dict[str, torch.Tensor]:
    """An ArrayRecord in ``wire_dtype`` -> fp32 tensors (one sentence if it is in another dtype)."""
    expected = "int16" if wire_dtype == "bfloat16" else "float32"
    for name, array in arrays.items():
        if array.dtype != expected:
            raise Zk0Error(f"Array {name!r} arrived as {array.dtype}; wire-dtype={wire_dtype} sends {expected}.")
    tensors = arrays.to_torch_state_dict()
    if wire_dtype == "float32":
        return tensors
    return {name: t.view(torch.bfloat16).float() for name, t in tensors.items()}
