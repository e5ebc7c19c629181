"""The warm worker's side of a message, without a federation: what crosses its socket, and what
the ClientApp does when no worker can be had. (Real SuperNodes with real workers run in
tests/test_deployment.py.)"""

from __future__ import annotations

import contextlib
import os
import socket
import tempfile
import threading

import numpy as np
import pytest
import torch
from flwr.app import ArrayRecord, ConfigRecord, Context, Message, MessageType, MetricRecord, RecordDict

from zk0 import app_fingerprint, client_app
from zk0.deployment import worker


def through_socket(content: RecordDict) -> RecordDict:
    """``content`` sent the way the proxy and the worker send message contents, and read back."""
    here, there = socket.socketpair()
    received = {}
    reader = threading.Thread(target=lambda: received.setdefault("content", worker._recv_records(there)))
    reader.start()
    worker._send_records(here, content)
    reader.join(timeout=60)
    return received["content"]


def test_message_contents_cross_the_socket_unchanged():
    weights = {"a": torch.randn(3, 4).to(torch.bfloat16).view(torch.int16), "b": torch.randn(5)}
    content = RecordDict(
        {
            "arrays": ArrayRecord(weights),
            "none": ArrayRecord(),
            "config": ConfigRecord({"server-round": 3, "run-name": "r"}),
            "metrics": MetricRecord({"loss": 0.5}),
        }
    )
    back = through_socket(content)
    assert set(back) == set(content)
    for name, tensor in weights.items():
        assert np.array_equal(back["arrays"][name].numpy(), tensor.numpy())
        assert back["arrays"][name].dtype == content["arrays"][name].dtype
    assert len(back["none"]) == 0
    assert dict(back["config"]) == {"server-round": 3, "run-name": "r"} and dict(back["metrics"]) == {"loss": 0.5}


def test_a_worker_that_cannot_start_leaves_the_message_to_the_clientapp(
    tmp_path, monkeypatch, registry, flower_task, isolated_logging
):
    """A socket folder others may write in is refused; the message is answered in this process instead."""
    from loguru import logger

    from zk0.config import RunConfig
    from zk0.federation.client import build_client
    from zk0.federation.wire import decode, encode
    from zk0.learning.policy import backbone_fingerprint, trainable_tensors

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    shared = tmp_path / f"zk0-{os.getuid()}"
    shared.mkdir()
    shared.chmod(0o777)
    run = RunConfig(batch_size=2, local_steps=1)
    server = build_client(run, registry.clients[0], registry.model_cameras())
    config = {
        "server-round": 1, "proximal-mu": 0.0, "run-name": "r1", "app-fingerprint": app_fingerprint(),
        "backbone-fingerprint": backbone_fingerprint(server.bundle),
    }  # fmt: skip
    message = Message(
        content=RecordDict(
            {"arrays": encode(trainable_tensors(server.bundle), run.wire_dtype), "config": ConfigRecord(config)}
        ),
        dst_node_id=9,
        message_type=MessageType.TRAIN,
    )
    node_config = {"partition-id": 0, "output-dir": str(tmp_path / "owner"), "warm-worker": True}
    context = Context(
        run_id=5, node_id=9, node_config=node_config, state=RecordDict(), run_config={"batch-size": 2, "local-steps": 1}
    )
    warnings = []
    sink = logger.add(lambda m: warnings.append(str(m)), level="WARNING")
    try:
        reply = client_app._handle("train", message, context)
    finally:
        with contextlib.suppress(ValueError):  # the client's setup_logging replaces loguru's handlers
            logger.remove(sink)
    assert any("not a private folder" in w and "in the ClientApp process instead" in w for w in warnings)
    metrics = reply["metrics"]
    assert metrics["num-examples"] == 2 and metrics["worker-s"] == 0.0
    assert set(decode(reply["arrays"], run.wire_dtype)) == set(server.bundle.trainable_names)
    assert not list(shared.iterdir()), "no worker was started in the shared folder"


def test_the_private_folder_is_private_whoever_creates_it_first(tmp_path, monkeypatch):
    """On a new machine a SuperNode registers before any worker starts: the folder it creates is the
    workers' private folder (mode 0700), one of this user's left readable is tightened, and one that
    others may write in, or a link, is refused in one sentence."""
    from zk0.common import machine
    from zk0.common.errors import Zk0Error

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    private = tmp_path / f"zk0-{os.getuid()}"
    machine.register(machine.registry_folder())  # first use: a SuperNode registers
    assert (private.stat().st_mode & 0o777) == 0o700 and (private / "supernodes" / str(os.getpid())).is_file()
    assert worker.socket_path(2**64 - 1, 7) == private / "ffffffffffffffff-7.sock"

    private.chmod(0o755)  # as zk0 before this fix left it
    worker.socket_path(1, 2)
    assert (private.stat().st_mode & 0o777) == 0o700

    private.chmod(0o777)
    with pytest.raises(worker.WorkerUnavailable, match="not a private folder of this user"):
        worker.socket_path(1, 2)
    with pytest.raises(Zk0Error, match=r"^\S+ is not a private folder of this user .*set TMPDIR"):
        machine.registry_folder()

    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / private.name).symlink_to(private)
    monkeypatch.setattr(tempfile, "tempdir", str(linked))
    private.chmod(0o700)
    with pytest.raises(worker.WorkerUnavailable, match="not a private folder of this user"):
        worker.socket_path(1, 2)
