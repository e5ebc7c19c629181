"""ClientApp wiring that needs no federation: dataset selection and optional W&B."""

from __future__ import annotations

import pytest
from flwr.app import Context, RecordDict

from zk0.client_app import dataset_index
from zk0.config import RunConfig
from zk0.registry import RegistryError
from zk0.tracking import Tracker


def context(node_config: dict) -> Context:
    return Context(run_id=1, node_id=7, node_config=node_config, state=RecordDict(), run_config={})


def test_node_config_names_the_dataset_else_partition_id(registry):
    assert dataset_index(registry, context({"partition-id": 2, "num-partitions": 4})) == 2
    assert dataset_index(registry, context({"dataset": "synth-so101-reach"})) == 3
    assert dataset_index(registry, context({"dataset": "zk0/synth_so100_stacking"})) == 1
    with pytest.raises(RegistryError, match="role 'server'"):
        dataset_index(registry, context({"dataset": "synth-so100-eval"}))
    with pytest.raises(RegistryError, match="Partition id 9"):
        dataset_index(registry, context({"partition-id": 9}))


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
