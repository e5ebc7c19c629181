"""The SuperNode's warm worker: the client stays built between messages of a run.

Flower (1.41, 1.42) runs every message a SuperNode receives in a fresh ``flwr-clientapp`` process.
Building SmolVLA, opening the dataset and importing lerobot there for every message cost more
than the local steps of a short round. So, on a SuperNode started by ``zk0 supernode`` (node
config ``warm-worker = true``), the ClientApp stays a light proxy: the first message of a run
starts one worker process for this run and node, and every message is handed to it over a
Unix socket that only this user can open. The worker keeps the policy, optimizer, data loader
and frame cache (and their GPU memory) for the whole run and answers with ``zk0.federation.client.handle``,
exactly what an in-process client does. Flower still carries every message.

The worker is started from the submitted app's own folder (the ``zk0`` the proxy was loaded
from), so it runs the submitted code, not the owner's installed copy. It exits after the run's
last message, when its SuperNode stops, or after ``IDLE_S`` without a message, and so gives
back the GPU. If it cannot start or dies, the proxy handles the message in its own process (the
old way: slower, but the run goes on); training continues from the data position kept in
``Context.state`` (the optimizer's moments start again: they lived in the worker).

This module imports no torch or lerobot: the proxy must stay cheap to start.
"""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

from flwr.app import Array, ArrayRecord, Context, RecordDict
from flwr.common.serde import context_from_proto, context_to_proto, recorddict_from_proto, recorddict_to_proto
from flwr.proto.message_pb2 import Context as ProtoContext
from flwr.proto.recorddict_pb2 import RecordDict as ProtoRecordDict
from loguru import logger

from zk0.common import machine
from zk0.common.errors import Zk0Error

IDLE_S = 3600.0  # Flower's default phase timeout: a gpu-serial round can keep a client waiting this long
START_TIMEOUT_S = 600.0  # imports and the first model build on a slow machine
WATCH_S = 2.0  # how often an idle worker checks that its SuperNode is still there


class WorkerUnavailable(RuntimeError):
    """The worker could not be started or reached, or died during a message."""


def enabled(node_config: dict) -> bool:
    return bool(node_config.get("warm-worker", False))


def socket_path(run_id: int, node_id: int) -> Path:
    """One socket per run and node, in a folder only this user may enter (refused otherwise)."""
    try:
        folder = machine.private_folder()
    except Zk0Error as err:
        raise WorkerUnavailable(f"{str(err).rstrip('.')}; not starting a worker there") from None
    # Hexadecimal: Flower's ids are 64-bit, and a Unix socket's path has 104-108 bytes in all.
    return folder / f"{run_id:x}-{node_id:x}.sock"


# Framing: each part is an 8-byte big-endian length and its bytes. A RecordDict travels as a JSON
# header describing its arrays, a protobuf of everything else (configs, metrics: small), and each
# array's bytes as they are: Flower's protobuf path copies 200 MB of weights four times.
def _send(sock: socket.socket, *parts: bytes) -> None:
    for part in parts:
        sock.sendall(struct.pack("!Q", len(part)))
        sock.sendall(part)


def _send_records(sock: socket.socket, content: RecordDict) -> None:
    rest, arrays, payloads = RecordDict(), [], []
    for key, record in content.items():
        if isinstance(record, ArrayRecord):
            arrays.append([key, [[name, a.dtype, list(a.shape), a.stype] for name, a in record.items()]])
            payloads += [a.data for a in record.values()]
        else:
            rest[key] = record
    _send(sock, json.dumps(arrays).encode(), recorddict_to_proto(rest).SerializeToString(), *payloads)


def _recv_records(sock: socket.socket) -> RecordDict:
    arrays = json.loads(_recv(sock))
    content = recorddict_from_proto(ProtoRecordDict.FromString(_recv(sock)))
    for key, described in arrays:
        content[key] = ArrayRecord(
            {name: Array(dtype, tuple(shape), stype, _recv(sock)) for name, dtype, shape, stype in described}
        )
    return content


def _recv(sock: socket.socket) -> bytes:
    size = struct.unpack("!Q", _recv_exact(sock, 8))[0]
    return bytes(_recv_exact(sock, size))


def _recv_exact(sock: socket.socket, size: int) -> bytearray:
    buffer = bytearray(size)
    view, got = memoryview(buffer), 0
    while got < size:
        n = sock.recv_into(view[got:])
        if n == 0:
            raise ConnectionError("the worker closed the connection")
        got += n
    return buffer


# The proxy's side (the flwr-clientapp process).
def call(kind: str, content: RecordDict, context: Context, arrived: float) -> tuple[RecordDict, float]:
    """Have this run's worker answer one message that reached this machine at ``arrived`` (Unix
    time: its ClientApp process's start); ``context.state`` takes the worker's update.

    Returns the reply and the seconds the worker spent on it. A ``Zk0Error`` in the worker comes
    back as the same one sentence; ``WorkerUnavailable`` means the caller should work in-process.
    """
    path = socket_path(context.run_id, context.node_id)  # before the try: it raises WorkerUnavailable itself
    connecting = time.time()
    with _connect(path) as sock:
        # Starting the worker (round 1's imports) is not the round's work, as building the client is not.
        arrived += time.time() - connecting
        try:
            header = json.dumps({"kind": kind, "arrived": arrived}).encode()
            _send(sock, header, context_to_proto(context).SerializeToString())
            _send_records(sock, content)
            status = json.loads(_recv(sock))
            if not status["ok"]:
                raise (Zk0Error if status["user-error"] else RuntimeError)(status["error"])
            updated = _recv(sock)
            reply = _recv_records(sock)
        except (ConnectionError, OSError) as err:
            raise WorkerUnavailable(f"the warm worker at {path} stopped during the message ({err})") from err
    context.state = context_from_proto(ProtoContext.FromString(updated)).state
    return reply, float(status["worker-s"])


def _connect(path: Path) -> socket.socket:
    """A connection to the worker at ``path``, starting it first if none listens there."""
    try:
        return _open(path)
    except (FileNotFoundError, ConnectionRefusedError):
        path.unlink(missing_ok=True)  # a worker that died leaves its socket file
    process = _spawn(path)
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            tail = path.with_suffix(".log").read_text(errors="replace")[-2000:]
            raise WorkerUnavailable(f"the warm worker exited with code {process.returncode}: {tail}")
        try:
            return _open(path)
        except (FileNotFoundError, ConnectionRefusedError):
            time.sleep(0.05)
    process.kill()
    raise WorkerUnavailable(f"the warm worker did not listen at {path} within {START_TIMEOUT_S:.0f} s")


def _open(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(str(path))
    except OSError:
        sock.close()
        raise
    return sock


def _spawn(path: Path) -> subprocess.Popen:
    """Start the worker from the folder this ``zk0`` was loaded from (the submitted app)."""
    app_root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (app_root, os.environ.get("PYTHONPATH")) if p)}
    log = path.with_suffix(".log").open("w")
    logger.info("Starting the warm worker for this run ({})", path)
    return subprocess.Popen(
        [sys.executable, "-m", "zk0.deployment.worker", str(path), str(os.getppid())],
        env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip


# The worker's side.
def serve(path: Path, supernode_pid: int) -> None:
    """Answer messages on ``path`` until the run's last message, the SuperNode's exit or ``IDLE_S``."""
    from zk0.artifacts.logs import setup_logging
    from zk0.federation import client  # the heavy imports (torch, lerobot) happen here, in the worker only

    setup_logging("worker")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(4)
    server.settimeout(WATCH_S)
    logger.info("Warm worker {} ready at {} (SuperNode process {})", os.getpid(), path, supernode_pid)
    last = time.monotonic()
    try:
        while True:
            try:
                conn, _ = server.accept()
            except TimeoutError:
                if not _alive(supernode_pid) or time.monotonic() - last > IDLE_S:
                    logger.info("Warm worker {}: SuperNode gone or idle; exiting.", os.getpid())
                    return
                continue
            with conn:
                conn.settimeout(None)
                finished = _answer(conn, client)
            last = time.monotonic()
            if finished:
                logger.info("Warm worker {}: the run's last message is answered; exiting.", os.getpid())
                return
    finally:
        server.close()
        path.unlink(missing_ok=True)
        client.release_sessions()


def _answer(conn: socket.socket, client) -> bool:
    """Answer one message; True when it was the run's last one for this client."""
    header = json.loads(_recv(conn))
    context = context_from_proto(ProtoContext.FromString(_recv(conn)))
    content = _recv_records(conn)
    started = time.perf_counter()
    try:
        reply = client.handle(header["kind"], content, context, keep_optimizer=False, arrived=header["arrived"])
    except Exception as err:  # sent to the proxy, which raises it in the ClientApp as Flower expects
        user = isinstance(err, Zk0Error)
        if not user:
            logger.exception("Warm worker: the {} message failed", header["kind"])
        _send(conn, json.dumps({"ok": False, "user-error": user, "error": str(err)}).encode())
        return False
    status = {"ok": True, "worker-s": time.perf_counter() - started}
    _send(conn, json.dumps(status).encode(), context_to_proto(context).SerializeToString())
    _send_records(conn, reply)
    return _is_last(header["kind"], content, context)


def _is_last(kind: str, content: RecordDict, context: Context) -> bool:
    """The final round's evaluation (or its training, when the run never evaluates on clients)."""
    rounds = int(context.run_config.get("num-server-rounds", 1))
    last_round = int(content["config"]["server-round"]) >= rounds
    return last_round and (kind == "evaluate" or float(context.run_config.get("fraction-evaluate", 1.0)) == 0.0)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


if __name__ == "__main__":
    serve(Path(sys.argv[1]), int(sys.argv[2]))
