"""ClientApp wiring that needs no federation: dataset selection and optional W&B."""

from __future__ import annotations

import pytest

from zk0.artifacts.tracking import Tracker
from zk0.config import RunConfig
from zk0.data.registry import RegistryError
from zk0.federation.client import client_index


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


def test_a_client_refuses_a_server_running_other_code_and_logs_in_its_own_folder(tmp_path, isolated_logging):
    from flwr.app import ArrayRecord, ConfigRecord, Context, RecordDict

    from zk0 import app_fingerprint
    from zk0.federation.client import handle
    from zk0.learning.policy import PolicyError

    node_config = {"dataset": "synth-so100-stacking", "output-dir": str(tmp_path / "owner")}
    context = Context(run_id=1, node_id=7, node_config=node_config, state=RecordDict(), run_config={"batch-size": 2})
    config = {"app-fingerprint": "0.0.9+0123456789ab", "backbone-fingerprint": "?", "run-name": "2026-01-01_00-00-00"}
    content = RecordDict(
        {"config": ConfigRecord({**config, "server-round": 1, "proximal-mu": 0.0}), "arrays": ArrayRecord()}
    )
    with pytest.raises(PolicyError) as refused:
        handle("train", content, context)
    assert str(refused.value) == (
        f"Client 1 (synth-so100-stacking) runs zk0 {app_fingerprint()}, the server runs zk0 0.0.9+0123456789ab; "
        "every party must run the submitted app's code."
    )
    log = tmp_path / "owner" / "2026-01-01_00-00-00" / "clients" / "client_1" / "client.log"
    assert "Opened synth-so100-stacking" in log.read_text()


def test_a_process_keeps_the_sessions_of_its_four_latest_nodes(tmp_path, isolated_logging):
    """A simulation's actor may run any of 64 owners: it keeps only the latest four built, and an
    owner met again is moved to the back of the line, not rebuilt."""
    from flwr.app import ConfigRecord, Context, RecordDict

    from zk0.federation import client

    config = ConfigRecord({"run-name": "2026-01-01_00-00-00", "server-round": 1})
    run_config = {"batch-size": 2, "output-dir": str(tmp_path)}
    client.release_sessions()
    try:
        for node in (1, 2, 3, 4, 1, 5, 6):
            context = Context(
                run_id=1,
                node_id=node,
                node_config={"partition-id": node % 4},
                state=RecordDict(),
                run_config=run_config,
            )
            client.session_for(context, config)
        assert [node for _, node in client._SESSIONS] == [4, 1, 5, 6]
    finally:
        client.release_sessions()
    assert not client._SESSIONS


def test_the_time_budget_counts_the_evaluation_the_train_message_carries(tmp_path, isolated_logging):
    """``local-time-s`` bounds a client's whole answer: the training gets what the evaluation of
    the received model (asked for with the train message) and the time since the message reached
    the machine (a warm worker's ClientApp process starting) left of it, so a slow owner's round
    lasts about the budget, not the budget plus its evaluation."""
    import time

    from flwr.app import ConfigRecord, Context, RecordDict

    from zk0 import app_fingerprint
    from zk0.federation import client
    from zk0.federation.wire import EVALUATE_ROUND, EVALUATION, encode
    from zk0.learning.policy import trainable_tensors

    budget = 3600.0
    run_config = {"batch-size": 2, "output-dir": str(tmp_path), "local-steps": 2, "local-time-s": budget}
    context = Context(run_id=1, node_id=1, node_config={"partition-id": 0}, state=RecordDict(), run_config=run_config)
    config = {"run-name": "2026-01-01_00-00-00", "server-round": 2, "proximal-mu": 0.0, EVALUATE_ROUND: 1}
    client.release_sessions()
    try:
        session, _ = client.session_for(context, ConfigRecord(config))
        config |= {"app-fingerprint": app_fingerprint(), "backbone-fingerprint": session.fingerprint}
        arrays = encode(trainable_tensors(session.bundle), session.run.wire_dtype)
        message = RecordDict({"config": ConfigRecord(config), "arrays": arrays})
        reply = client.handle("train", message, context)
        arrived = client.handle("train", message, context, arrived=time.time() - 60)  # a minute ago
    finally:
        client.release_sessions()
    metrics = next(iter(reply.metric_records.values()))
    assert "action-mse" in reply[EVALUATION] and metrics["local-steps"] == 2
    assert 0 < metrics["evaluate-s"] <= budget - metrics["budget-s"] < metrics["handler-s"]
    late = next(iter(arrived.metric_records.values()))
    assert 60 + late["evaluate-s"] <= budget - late["budget-s"] < 60 + late["handler-s"]
    assert client.training_budget(0.0, 5.0) == 0.0  # no budget stays none
    assert 0 < client.training_budget(10.0, 12.0) < 1e-6  # a budget spent on evaluating still trains a step


def test_a_run_name_that_is_a_path_is_refused():
    from zk0.config import ConfigError
    from zk0.federation.client import client_log

    assert client_log({"output-dir": "/data/zk0"}, RunConfig(), "run-1", 2).as_posix() == (
        "/data/zk0/run-1/clients/client_2/client.log"
    )
    for name in ("../../etc", "/tmp/x", ".."):
        with pytest.raises(ConfigError, match="expected a plain folder name"):
            client_log({}, RunConfig(), name, 0)
