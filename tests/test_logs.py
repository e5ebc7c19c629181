"""Records from the standard `logging` module (Flower, lerobot, Ray) come out through loguru."""

from __future__ import annotations

import logging

from loguru import logger

from zk0.logs import setup_logging


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
