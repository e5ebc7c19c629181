"""bf16 on the wire: raw 16-bit patterns through NumPy, fp32 on both ends, FedAvg on decoded values."""

from __future__ import annotations

import pytest
import torch

from zk0.errors import Zk0Error
from zk0.wire import decode, encode


def test_bf16_round_trip_is_the_bf16_rounding_and_halves_the_bytes():
    tensors = {"w": torch.randn(64, 33), "b": torch.tensor([1.0, -2.5e-3, 3.14159, 1e-8])}
    wire = encode(tensors, "bfloat16")
    assert {a.dtype for a in wire.values()} == {"int16"}
    back = decode(wire, "bfloat16")
    for name, tensor in tensors.items():
        assert back[name].dtype == torch.float32
        torch.testing.assert_close(back[name], tensor.to(torch.bfloat16).float(), rtol=0, atol=0)
    full = encode(tensors, "float32")
    payload = sum(t.numel() for t in tensors.values())
    assert wire.count_bytes() - 2 * payload == full.count_bytes() - 4 * payload  # same overhead, half the data


def test_a_mismatched_dtype_is_named():
    with pytest.raises(Zk0Error, match="'w' arrived as float32; wire-dtype=bfloat16 sends int16"):
        decode(encode({"w": torch.ones(2)}, "float32"), "bfloat16")


def test_fedavg_averages_decoded_values(flower_task):
    from tests.test_aggregation import Recorder, reply
    from zk0.aggregation import ValidatingStrategy, array_signature
    from zk0.server_optimisers import make_strategy

    template = {"a": torch.zeros(2, 3), "b": torch.zeros(4)}
    strategy = ValidatingStrategy(
        make_strategy("fedavg", 0.0, 0.9, min_train_nodes=2),
        expected=array_signature(encode(template, "float32")),
        evaluates_in=lambda _: True,
        observer=Recorder([]),
        last_round=1,
        wire_dtype="bfloat16",
    )
    strategy.current = encode(template, "float32")
    updates = [
        {"a": torch.full((2, 3), 1.001), "b": torch.full((4,), 7.0)},
        {"a": torch.full((2, 3), 3.0), "b": torch.zeros(4)},
    ]
    replies = [
        reply(i + 1, encode(u, "bfloat16"), examples=n) for i, (u, n) in enumerate(zip(updates, [1, 3], strict=True))
    ]
    result, _ = strategy.aggregate_train(1, replies)
    expected = (updates[0]["a"].to(torch.bfloat16).float() * 1 + updates[1]["a"] * 3) / 4
    assert result["a"].dtype == "float32"
    torch.testing.assert_close(torch.from_numpy(result["a"].numpy()), expected)
