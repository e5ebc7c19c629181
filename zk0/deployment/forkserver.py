"""Flower's task processes forked from one that has already imported what they need, instead of started afresh.

Flower's SuperExec starts a new process for every task: a ``flwr-clientapp`` for every message on
a SuperNode (both isolation modes, flwr 1.41-1.43), a ``flwr-serverapp`` or ``flwr-simulation``
for every run on a SuperLink. Each pays Python's start and its imports before it does anything:
Flower's (FastAPI, SQLAlchemy, httpx, the protobufs; about a second of CPU, two on a busy machine)
for a ClientApp, every round; Flower's, PyTorch's and lerobot's (about 10 s of CPU on 2 cores, of
the 39 a minimal two-round simulation took) for a ServerApp, every run. zk0's SuperExec
(``python -m zk0.deployment.superexec``) keeps a fork server: a process that imported those
once and forks a child per task, which runs Flower's command with the arguments Flower chose
(its token, TLS, parent pid).

A SuperLink's fork server also forks, once, a Ray worker fork server: a simulated run's Ray
starts each worker (each actor's process, which would import PyTorch and lerobot again) through
``zk0.deployment.rayworker``, which asks it over a Unix socket for a forked worker.

The child is still Flower's task process: it pulls the task, unpacks the submitted FAB and
imports the app's code from it. The fork server holds only third-party modules and no ``zk0``
module a child could reuse (each child forgets them before Flower loads the app), so the code
that runs is the submitted app's, and the app fingerprint check sees it. The fork server starts
no thread of its own (a library it imports may start a helper thread, such as jemalloc's
background thread, which registers its own fork handlers), so forking it is safe; a child resets
the signals and output the fork server changed.
"""

from __future__ import annotations

import importlib
import json
import os
import runpy
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import IO

from loguru import logger

from zk0.deployment import rayworker

# What a zk0 ServerApp or ClientApp imports that takes seconds, loaded once by a SuperLink's fork
# server (and shared by its Ray worker fork server): only third-party modules (the app's own come
# from the FAB). Neither MuJoCo (it chooses its GL backend from MUJOCO_GL when imported) nor Ray
# (importing it fixes its core worker's settings from this process's environment: a forked
# worker would lack the RAY_JOB_ID that Ray gives each one).
SERVER_LIBRARIES = (
    "torch",
    "lerobot.datasets.lerobot_dataset",
    "lerobot.datasets.factory",
    "lerobot.policies.factory",
    "lerobot.processor",
    "matplotlib.figure",
)


RAY_WORKER_SERVER = "zk0-ray-forks"  # the Ray worker fork server's process name (15 characters at most)


class ForkServer:
    """The SuperExec's side: start the fork server once, then hand it each task's arguments. A
    SuperNode's serves ClientApps; a SuperLink's (``server``) serves ServerApps and simulations."""

    def __init__(self, server: bool = False) -> None:
        self.what = "ServerApp" if server else "ClientApp"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "zk0.deployment.forkserver", *(["--server"] if server else [])],
            stdin=subprocess.PIPE,
            text=True,
        )
        self.gone = False

    def start(self, args: list[str], quiet: bool) -> bool:
        """Ask for a process running ``args`` (``flwr-clientapp ...``, ``flwr-simulation ...``);
        False if the fork server is gone (the caller then starts the process as Flower would)."""
        if self.gone:
            return False
        try:
            self.process.stdin.write(json.dumps({"args": args, "quiet": quiet}) + "\n")
            self.process.stdin.flush()
            return True
        except OSError:  # a broken pipe: the fork server exited
            logger.warning(
                "zk0: the {} fork server exited (code {}); each {} process now starts afresh, as Flower starts it.",
                self.what,
                self.process.wait(),
                self.what,
            )
            self.gone = True
            return False


def serve(requests: IO[str], server: bool = False) -> None:
    """Import what Flower's task commands run (with ``server``, ServerApps' and simulations', and
    ``SERVER_LIBRARIES``), then fork a task for each request until the SuperExec closes the pipe
    (it exited, or was killed)."""
    from flwr.supernode.cli import flwr_clientapp

    from zk0 import internals

    commands = {"flwr-clientapp": flwr_clientapp}
    if server:
        from flwr.simulation.app import flwr_simulation
        from flwr.superlink.cli import flwr_serverapp

        commands |= {"flwr-serverapp": flwr_serverapp, "flwr-simulation": flwr_simulation}
        for name in SERVER_LIBRARIES:
            importlib.import_module(name)
    internals.shorten_object_pull_backoff()  # the arrays a task pulls from its SuperNode or SuperLink
    _forget_zk0()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group: the SuperExec ends this
    ray_workers = None  # started with the first simulation (a deployment's SuperLink runs none)
    signal.signal(signal.SIGCHLD, _reap)
    for line in requests:
        request = json.loads(line)
        command = commands.get(request["args"][0])
        if command is None:
            logger.error("zk0: this fork server starts {}, not {!r}.", ", ".join(commands), request["args"][0])
            continue
        if request["args"][0] == "flwr-simulation" and ray_workers is None:
            ray_workers = start_ray_worker_server() or ""
        with warnings.catch_warnings():  # Python warns of any thread; see the module's docstring
            warnings.filterwarnings("ignore", "This process .* is multi-threaded", DeprecationWarning)
            child = os.fork()
        if child == 0:
            if ray_workers and request["args"][0] == "flwr-simulation":
                internals.start_ray_workers_with(
                    f"{sys.executable} -m zk0.deployment.rayworker", {rayworker.SOCKET_ENV: ray_workers}
                )
            _run_task(command, request["args"], request["quiet"])


def _run_task(command, args: list[str], quiet: bool) -> None:
    """In the forked child: become Flower's ``args`` (``command`` is its entry point) as a fresh
    process would be, then exit."""
    code = 1
    try:
        for sig in (signal.SIGINT, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)  # the fork server's stdin is the SuperExec's pipe
        if quiet:
            os.dup2(null, 1)
            os.dup2(null, 2)
        os.close(null)
        sys.argv = args
        command()
        code = 0
    except SystemExit as done:
        code = _exit_code(done)
    except BaseException:
        logger.exception("The forked {} process failed", args[0])
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _take_environment(env: dict[str, str]) -> None:
    """Make this process's environment ``env``, changing only what differs: Ray names its workers
    (``ray::ClientAppActor``) by rewriting the memory of their command line and environment, which
    fails where the first variable was removed or the whole environment replaced."""
    for name in [name for name in os.environ if name not in env]:
        del os.environ[name]
    os.environ.update({name: value for name, value in env.items() if os.environ.get(name) != value})


def _exit_code(done: SystemExit) -> int:
    return done.code if isinstance(done.code, int) else (0 if done.code is None else 1)


def start_ray_worker_server() -> str | None:
    """Fork the Ray worker fork server from this process (whose imports it shares), listening on a
    socket in a private folder; return the socket's path, or None where the platform has no such
    socket (then Ray starts its workers itself)."""
    if not hasattr(socket, "SOCK_SEQPACKET") or sys.platform != "linux":
        return None
    path = Path(tempfile.mkdtemp(prefix="zk0-ray-")) / "workers.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        listener.bind(str(path))
    except OSError:  # a TMPDIR too long for a socket's path
        listener.close()
        path.parent.rmdir()
        return None
    listener.listen(16)
    if os.fork() == 0:
        try:
            Path("/proc/self/comm").write_text(RAY_WORKER_SERVER)  # its name, for `ps` and bench.watch
            _serve_ray_workers(listener)
        except SystemExit:
            pass
        except BaseException:
            logger.exception("zk0: the Ray worker fork server failed; Ray starts its workers itself from now on")
        finally:
            path.unlink(missing_ok=True)
            path.parent.rmdir()
            os._exit(0)
    listener.close()
    return str(path)


def _serve_ray_workers(listener: socket.socket) -> None:
    """Fork a Ray worker for each connecting ``zk0.deployment.rayworker``, hand it the worker's exit
    code, and kill a worker whose ``rayworker`` went (Ray killed it); end with the fork server."""
    parent = os.getppid()
    wake_read, wake_write = socket.socketpair()
    wake_write.setblocking(False)
    signal.set_wakeup_fd(wake_write.fileno())  # a SIGCHLD wakes the select below
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.signal(signal.SIGTERM, _stop)  # stopping the SuperLink terminates its tree: remove the socket
    selector = selectors.DefaultSelector()
    selector.register(listener, selectors.EVENT_READ)
    selector.register(wake_read, selectors.EVENT_READ)
    workers: dict[int, socket.socket] = {}
    while os.getppid() == parent:  # the fork server (parent) ends when its SuperExec does
        for key, _ in selector.select(timeout=1.0):
            if key.fileobj is listener:
                conn = listener.accept()[0]
                if pid := _fork_ray_worker(conn, [listener, wake_read, wake_write, *workers.values()]):
                    workers[pid] = conn
                    selector.register(conn, selectors.EVENT_READ, pid)
            elif key.fileobj is wake_read:
                wake_read.recv(4096)
            else:  # the rayworker closed its end: Ray killed it
                selector.unregister(key.fileobj)
                _kill(key.data)
        for pid, code in _exited():
            if (conn := workers.pop(pid, None)) is not None:
                _close(selector, conn, code)


def _stop(_signum: int, _frame: object) -> None:
    raise SystemExit(0)


def _close(selector: selectors.BaseSelector, conn: socket.socket, code: int) -> None:
    """Tell a worker's ``rayworker`` its exit code and let it go."""
    try:
        selector.unregister(conn)
    except KeyError:
        pass
    try:
        conn.send(str(code).encode())
    except OSError:
        pass
    conn.close()


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _exited() -> list[tuple[int, int]]:
    """The workers that have exited since last asked, with their exit codes."""
    done = []
    try:
        while (found := os.waitpid(-1, os.WNOHANG))[0]:
            done.append((found[0], os.waitstatus_to_exitcode(found[1])))
    except ChildProcessError:
        pass
    return done


def _fork_ray_worker(conn: socket.socket, inherited: list[socket.socket]) -> int | None:
    """Fork the worker a ``rayworker`` asked for and return its pid (None, the connection closed,
    if the ``rayworker`` went before asking); in the child, become it and never return."""
    message, fds, _, _ = socket.recv_fds(conn, rayworker.MAX_REQUEST, 3)
    try:
        request = json.loads(message) if len(fds) == 3 else None
    except ValueError:  # empty: it went before asking
        request = None
    child = None
    if request is not None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})  # the child must not stop as this server
        with warnings.catch_warnings():  # see the module's docstring
            warnings.filterwarnings("ignore", "This process .* is multi-threaded", DeprecationWarning)
            child = os.fork()
        if child == 0:
            _become_ray_worker(request, fds, [conn, *inherited])
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    for fd in fds:
        os.close(fd)
    if child is None:
        conn.close()
    return child


def _become_ray_worker(request: dict, fds: list[int], inherited: list[socket.socket]) -> None:
    """In the forked child: Ray's worker, with the command line, environment, folder and standard
    streams Ray gave the ``rayworker`` (the fork server's ``inherited`` sockets closed), as
    ``python default_worker.py ...`` would start; then exit, whatever happens."""
    code = 1
    try:
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGINT, signal.SIGCHLD, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
        for sock in inherited:
            sock.close()
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request["cwd"])
        _take_environment(request["env"])
        args = request["args"]
        paths = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        sys.path[:] = [os.path.dirname(args[0]), *paths, *sys.path[1:]]
        if threads := os.environ.get("OMP_NUM_THREADS", "").strip():
            import torch

            torch.set_num_threads(int(threads))  # PyTorch read the fork server's at import
        sys.argv = args
        runpy.run_path(args[0], run_name="__main__")
        code = 0
    except SystemExit as done:
        code = _exit_code(done)
    except BaseException:
        logger.exception("The forked Ray worker failed")
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _forget_zk0() -> None:
    """Drop the installed ``zk0`` modules (this module's package), so a child imports the app's
    code from the submitted FAB, where Flower points ``sys.path``, not from this process."""
    for name in [n for n in sys.modules if n == "zk0" or n.startswith("zk0.")]:
        del sys.modules[name]


def _reap(_signum: int, _frame: object) -> None:
    """Collect finished task processes (Flower never waits for them either)."""
    try:
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass
    except ChildProcessError:
        pass


if __name__ == "__main__":
    serve(sys.stdin, server="--server" in sys.argv[1:])
