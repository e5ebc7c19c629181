"""ClientApp wiring that needs no federation: dataset selection and optional W&B."""

from __future__ import annotations

import pytest

from zk0.client import client_index
from zk0.config import RunConfig
from zk0.registry import RegistryError
from zk0.tracking import Tracker


def test_node_config_names_the_dataset_else_partition_id(registry):
    assert client_index(registry, {"partition-id": 2, "num-partitions": 4}) == 2
    assert client_index(registry, {"dataset": "synth-so101-reach"}) == 3
    assert client_index(registry, {"dataset": "zk0/synth_so100_stacking"}) == 1
    with pytest.raises(RegistryError, match="role 'server'"):
        client_index(registry, {"dataset": "synth-so100-eval"})
    with pytest.raises(RegistryError, match="Partition id 9"):
        client_index(registry, {"partition-id": 9})


def test_wandb_without_a_key_is_one_warning_not_a_failure(tmp_path, monkeypatch):
    from loguru import logger

    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    messages = []
    sink = logger.add(messages.append, level="WARNING")
    try:
        tracker = Tracker.start(RunConfig(use_wandb=True), tmp_path)
        tracker.log(1, {"server-evaluate": {"action-mse": 1.0}})
        tracker.finish()
    finally:
        logger.remove(sink)
    assert tracker.wandb_run is None
    assert len(messages) == 1 and "WANDB_API_KEY" in messages[0]
