"""Records from the standard `logging` module (Flower, lerobot, Ray) come out through loguru."""

from __future__ import annotations

import logging

from loguru import logger

from zk0.artifacts.logs import setup_logging


def emit_from_a_library():
    logging.getLogger("flwr").warning("from flower")
    logging.getLogger("lerobot.datasets").info("from lerobot")


def test_library_records_keep_their_real_caller(isolated_logging):
    setup_logging("test")
    records = []
    sink = logger.add(lambda message: records.append(message.record), level="INFO")
    try:
        emit_from_a_library()
        logging.getLogger("httpx").info("poll")  # silenced: one line per HTTP request otherwise
    finally:
        logger.remove(sink)
    assert [r["message"] for r in records] == ["from flower", "from lerobot"]
    assert {r["function"] for r in records} == {"emit_from_a_library"}
    assert [r["level"].name for r in records] == ["WARNING", "INFO"]
    assert all(r["extra"]["party"] == "test" for r in records)


def test_the_console_shows_zk0s_lines_for_a_person_and_the_files_keep_everything(
    isolated_logging, capsys, monkeypatch, tmp_path
):
    from zk0.artifacts.logs import add_file_sink, prints_to_log, say

    monkeypatch.delenv("ZK0_VERBOSE", raising=False)
    setup_logging("server")
    add_file_sink(tmp_path / "server.log", "server")
    say("Round {}/{}: 4 clients trained", 1, 8)
    zk0_module = logger.patch(lambda record: record.update(name="zk0.federation.aggregation"))
    zk0_module.warning("Round 3: client 1's update is 1e+03x the median of the others'")
    zk0_module.error("zk0: Run-config key 'local-steps' got 0; expected a value >= 1.")
    zk0_module.info("Round 1 train on synth: {'train-loss': 1.9}")  # per-client detail: the file only
    logger.warning("a warning of a module not zk0's")  # the file only
    emit_from_a_library()  # Flower's warning, lerobot's info: the file only
    logging.getLogger("flwr").error("Exit Code: 700")
    with prints_to_log("lerobot"):
        print("Reducing the number of VLM layers to 16 ...")
    console = capsys.readouterr()
    assert console.out == ""
    assert console.err.splitlines() == [
        "[zk0] Round 1/8: 4 clients trained",
        "[zk0] warning: Round 3: client 1's update is 1e+03x the median of the others'",
        "zk0: Run-config key 'local-steps' got 0; expected a value >= 1.",
        "[zk0] error in tests.test_logs: Exit Code: 700",
    ]
    logged = (tmp_path / "server.log").read_text()
    for line in ("Round 1 train on synth", "not zk0's", "from flower", "from lerobot", "lerobot:print:", "Reducing the number"):
        assert line in logged


def test_verbose_puts_every_record_on_the_console(isolated_logging, capsys, monkeypatch):
    monkeypatch.setenv("ZK0_VERBOSE", "1")
    setup_logging("server")
    emit_from_a_library()
    from zk0.artifacts.logs import prints_to_log

    with prints_to_log("lerobot"):
        print("Reducing the number of VLM layers to 16 ...")
    console = capsys.readouterr()
    assert console.out == "Reducing the number of VLM layers to 16 ...\n"
    assert "| WARNING | server | tests.test_logs:emit_from_a_library:" in console.err and "from lerobot" in console.err
