"""Weights on the wire: one packed array and its manifest, bf16 as raw 16-bit patterns through NumPy,
fp32 on both ends, FedAvg on decoded values."""

from __future__ import annotations

import pytest
import torch

from zk0.common.errors import Zk0Error
from zk0.federation.wire import MANIFEST, PACKED, decode, encode


def test_bf16_round_trip_is_the_bf16_rounding_and_halves_the_bytes():
    tensors = {"w": torch.randn(64, 33), "b": torch.tensor([1.0, -2.5e-3, 3.14159, 1e-8])}
    wire = encode(tensors, "bfloat16")
    assert wire[PACKED].dtype == "int16" and wire[PACKED].shape == (64 * 33 + 4,)
    back = decode(wire, "bfloat16")
    for name, tensor in tensors.items():
        assert back[name].dtype == torch.float32
        torch.testing.assert_close(back[name], tensor.to(torch.bfloat16).float(), rtol=0, atol=0)
    full = encode(tensors, "float32")
    payload = sum(t.numel() for t in tensors.values())
    assert wire.count_bytes() - 2 * payload == full.count_bytes() - 4 * payload  # same overhead, half the data


def test_a_mismatched_dtype_is_named():
    with pytest.raises(Zk0Error, match="The weights arrived as float32; wire-dtype=bfloat16 sends int16"):
        decode(encode({"w": torch.ones(2)}, "float32"), "bfloat16")


def test_every_tensor_travels_in_one_array_and_comes_back_in_its_shape():
    tensors = {"w": torch.randn(2, 3, 4), "scalar": torch.tensor(0.5), "empty": torch.zeros(0, 3), "b": torch.randn(7)}
    wire = encode(tensors, "float32")
    assert set(wire) == {PACKED, MANIFEST} and wire[PACKED].shape == (24 + 1 + 0 + 7,)
    back = decode(wire, "float32")
    assert list(back) == list(tensors)
    for name, tensor in tensors.items():
        assert back[name].shape == tensor.shape
        torch.testing.assert_close(back[name], tensor, rtol=0, atol=0)


def test_weights_that_are_not_zk0s_packing_are_named():
    from flwr.app import Array, ArrayRecord

    with pytest.raises(Zk0Error, match=r"arrived as arrays \['w'\]; zk0 sends 'zk0:packed' and 'zk0:manifest'"):
        decode(ArrayRecord({"w": torch.ones(2)}), "float32")
    wire = encode({"w": torch.ones(2, 3)}, "float32")
    cut = ArrayRecord({PACKED: Array(torch.ones(5).numpy()), MANIFEST: wire[MANIFEST]})
    with pytest.raises(Zk0Error, match="arrived with 5 values; their manifest describes 6"):
        decode(cut, "float32")


def test_fedavg_averages_decoded_values(flower_task):
    from flwr.app import ArrayRecord

    from tests.test_aggregation import Recorder, reply
    from zk0.federation.aggregation import ValidatingStrategy
    from zk0.federation.updates import array_signature
    from zk0.federation.server_optimisers import make_strategy

    template = {"a": torch.zeros(2, 3), "b": torch.zeros(4)}
    strategy = ValidatingStrategy(
        make_strategy("fedavg", 0.0, 0.9, min_train_nodes=2),
        expected=array_signature(ArrayRecord(template)),
        evaluates_in=lambda _: True,
        observer=Recorder([]),
        last_round=1,
        wire_dtype="bfloat16",
    )
    strategy.current = ArrayRecord(template)
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
