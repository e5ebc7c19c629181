"""loguru as the one logger; Flower's, lerobot's and Ray's ``logging`` records are routed into it.

An intercept handler on the root logger re-emits every standard-library record through
loguru with the record's own module, function and line, so server and client logs have
one format and the real caller. Flower installs its own handler on the ``flwr`` logger;
it is replaced so each line appears once.

The console is for a robot owner: zk0's own lines written for a person (``say``) and every
zk0 warning and error, each as ``[zk0] <sentence>``. Everything else (Flower's and Ray's lines,
per-client detail, libraries' prints) goes to ``server.log`` / ``client.log`` only, in full.
``ZK0_VERBOSE=1`` (``./train.sh --verbose``) puts every record back on the console, with its
time, level and caller, as the log files have them.

When a zk0 error (a user's mistake, already logged as its one sentence) ends a run, Flower
logs it again with its traceback. The console then shows Flower's line without the
traceback; the traceback goes to the log files only, at DEBUG.
"""

from __future__ import annotations

import contextlib
import errno
import inspect
import io
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from loguru import logger

from zk0.common.errors import Zk0Error

FORMAT = "{time:YYYY-MM-DD HH:mm:ss.SSS} | {level: <7} | {extra[party]} | {name}:{function}:{line} - {message}"
VERBOSE = "ZK0_VERBOSE"  # set (not "0"): every record on the console, as before zk0 had a console of its own
CONSOLE_PREFIX = "[zk0] "  # what train.sh keeps of a run's output when not verbose


def verbose() -> bool:
    """Whether this process shows every record on its console (``ZK0_VERBOSE``)."""
    return os.environ.get(VERBOSE, "0") not in ("", "0")


def say(message: str, *args: object) -> None:
    """Log a line written for the person running zk0: on the console, and in the log files."""
    logger.opt(depth=1).bind(console=True).info(message, *args)


def _own(record: dict) -> bool:
    return record["name"] is not None and record["name"].split(".")[0] == "zk0"


def for_a_person(record: dict) -> bool:
    """The console's records: lines ``say`` wrote, zk0's own warnings and errors (one sentence
    each), and any library's error (a run that fails says why); not the rest of Flower's, Ray's
    or lerobot's lines."""
    level = record["level"].no
    if record["extra"].get("console", False) or level >= logging.ERROR:
        return True
    return _own(record) and level >= logging.WARNING


def console_format(record: dict) -> str:
    """``[zk0] <sentence>``; a warning says so; a user's error keeps its ``zk0: `` prefix; a
    library's error names the library; tracebacks stay in the log files."""
    if record["message"].startswith("zk0: "):
        return "{message}\n"
    if not _own(record) and record["level"].no >= logging.ERROR:
        return CONSOLE_PREFIX + "error in {name}: {message}\n"
    warning = "warning: " if logging.WARNING <= record["level"].no < logging.ERROR else ""
    return CONSOLE_PREFIX + warning + "{message}\n"


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
    if verbose():
        _console_sink = logger.add(sys.stderr, level=level, format=FORMAT, backtrace=False, diagnose=False)
    else:
        _console_sink = logger.add(sys.stderr, level=level, format=console_format, filter=for_a_person)
    logging.basicConfig(handlers=[InterceptHandler()], level=0, force=True)
    logging.captureWarnings(True)  # Python warnings (Ray's FutureWarning, ...) become log records
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
        _LogFile(log_file),
        level="DEBUG",
        format=FORMAT,
        backtrace=False,
        diagnose=False,
        filter=lambda r: r["extra"].get("party") == party and (r["level"].no >= threshold or "traceback" in r["extra"]),
    )


class _LogFile:
    """A log file, line by line (simulation actors are killed at the end of a run), that a full disk
    silences instead of failing: the run's own sentence says which disk is full, and a log line
    that cannot be written is not worth loguru's traceback on the console."""

    def __init__(self, path: Path) -> None:
        self.file = open(path, "a", buffering=1, encoding="utf-8")  # noqa: SIM115  # closed by stop()

    def write(self, message: str) -> None:
        try:
            self.file.write(message)
        except OSError as err:
            if err.errno != errno.ENOSPC:
                raise

    def stop(self) -> None:
        with contextlib.suppress(OSError):
            self.file.close()


class _LineLogger(io.TextIOBase):
    """A text stream that logs each complete line it is given (at INFO, as ``caller``)."""

    def __init__(self, caller: str):
        self.caller, self.pending = caller, ""

    def write(self, text: str) -> int:
        self.pending += text
        *lines, self.pending = self.pending.split("\n")
        for line in filter(str.strip, lines):
            logger.patch(lambda r: r.update(name=self.caller, function="print")).info(line)
        return len(text)


@contextlib.contextmanager
def prints_to_log(caller: str) -> Iterator[None]:
    """What libraries ``print`` inside the block (lerobot's "Reducing the number of VLM layers")
    goes to the log files, not the console; verbose, it stays on the console."""
    if verbose():
        yield
        return
    stream = _LineLogger(caller)
    with contextlib.redirect_stdout(stream):
        yield
    stream.write("\n")


@contextlib.contextmanager
def native_output_to(log_file: Path) -> Iterator[io.TextIOWrapper]:
    """Send everything written to this process's stderr, by Python or by native libraries (FFmpeg's
    muxer lines, ``datasets``' progress bars), to ``log_file``; yield a stream on the real stderr
    for zk0's own progress. Verbose, nothing is redirected."""
    console = os.fdopen(os.dup(2), "w", buffering=1)
    if verbose():
        with console:
            yield console
        return
    log_file.parent.mkdir(parents=True, exist_ok=True)
    sys.stderr.flush()
    saved = os.dup(2)
    with open(log_file, "a") as target, console:
        os.dup2(target.fileno(), 2)
        try:
            yield console
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
