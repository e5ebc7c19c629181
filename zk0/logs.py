"""loguru as the one logger; Flower's, lerobot's and Ray's ``logging`` records are routed into it.

An intercept handler on the root logger re-emits every standard-library record through
loguru with the record's own module, function and line, so server and client logs have
one format and the real caller. Flower installs its own handler on the ``flwr`` logger;
it is replaced so each line appears once.

When a zk0 error (a user's mistake, already logged as its one sentence) ends a run, Flower
logs it again with its traceback. The console then shows Flower's line without the
traceback; the traceback goes to the log files only, at DEBUG.
"""

from __future__ import annotations

import inspect
import logging
import sys
from pathlib import Path

from loguru import logger

from zk0.errors import Zk0Error

FORMAT = "{time:YYYY-MM-DD HH:mm:ss.SSS} | {level: <7} | {extra[party]} | {name}:{function}:{line} - {message}"


class InterceptHandler(logging.Handler):
    """Send a ``logging`` record to loguru, keeping the original caller."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level: str | int = logger.level(record.levelname).name
        except ValueError:
            level = record.levelno
        frame, depth = inspect.currentframe(), 0
        while frame and (depth == 0 or frame.f_code.co_filename == logging.__file__):
            frame, depth = frame.f_back, depth + 1
        if record.exc_info and isinstance(record.exc_info[1], Zk0Error):
            logger.opt(depth=depth).log(level, record.getMessage())
            logger.bind(traceback=True).opt(depth=depth, exception=record.exc_info).debug("Where that error arose:")
            return
        logger.opt(depth=depth, exception=record.exc_info).log(level, record.getMessage())


_console_sink: int | None = None


def setup_logging(party: str, level: str = "INFO") -> None:
    """One console (stderr) sink per process; all third-party logging routed through loguru.

    Safe to call again (several simulated clients share a process): file sinks added since
    stay, only the console sink is replaced.
    """
    global _console_sink
    if _console_sink is None:
        logger.remove()  # loguru's default stderr handler
    else:
        logger.remove(_console_sink)
    logger.configure(extra={"party": party})
    _console_sink = logger.add(sys.stderr, level=level, format=FORMAT, backtrace=False, diagnose=False)
    logging.basicConfig(handlers=[InterceptHandler()], level=0, force=True)
    for name in ("flwr", "lerobot", "ray", "accelerate"):
        third_party = logging.getLogger(name)
        third_party.handlers = []
        third_party.propagate = True
    for chatty in ("httpx", "httpcore", "urllib3", "filelock"):  # one line per HTTP poll otherwise
        logging.getLogger(chatty).setLevel(logging.WARNING)


def add_file_sink(log_file: Path, party: str, level: str = "INFO") -> int:
    """Also write ``party``'s records (see ``logger.contextualize(party=...)``) to ``log_file``,
    and the tracebacks kept off the console.

    Several simulated clients can share one process, so each file keeps only its own party.
    """
    log_file.parent.mkdir(parents=True, exist_ok=True)
    threshold = logger.level(level).no
    return logger.add(
        log_file,
        level="DEBUG",
        format=FORMAT,
        backtrace=False,
        diagnose=False,
        buffering=1,  # line by line: simulation actors are killed at the end of a run
        filter=lambda r: r["extra"].get("party") == party and (r["level"].no >= threshold or "traceback" in r["extra"]),
    )
