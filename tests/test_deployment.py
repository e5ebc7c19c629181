"""Flower's Deployment Engine on loopback, as robot owners run it across machines: a TLS SuperLink
with SuperNode authentication, each SuperNode in its own working folder with its own outputs,
strangers refused, the submitted app's code running on every SuperNode, the client kept warm
between messages, and owners who leave, come back and join mid-run."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import psutil
import pytest

from zk0.data.registry import PROJECT_ROOT
from zk0.deployment.loopback import LoopbackFederation, loopback_federation, tool, warm_workers_of

pytestmark = pytest.mark.deployment

ROBOTS = {"robot-1": "synth-so100-pickplace", "robot-2": "synth-so100-stacking"}
MARKER = "Opened (submitted copy)"


@pytest.fixture(scope="module")
def federation(tmp_path_factory):
    """Two robots' SuperNodes with `zk0 supernode`'s defaults, on a temporary directory that starts
    empty: each registers there (to share the CPUs) before any warm worker exists, as on a new machine."""
    with loopback_federation(tmp_path_factory.mktemp("deployment"), ROBOTS) as fed:
        yield fed


def history(out: Path) -> tuple[Path, dict]:
    (run_dir,) = out.iterdir()
    return run_dir, json.loads((run_dir / "server" / "metrics_history.json").read_text())


def client_log(fed: LoopbackFederation, robot: str, run_dir: Path, index: int) -> str:
    """A client's log, where its SuperNode keeps it: under that robot's own output folder."""
    return (fed.root / robot / "outputs" / run_dir.name / "clients" / f"client_{index}" / "client.log").read_text()


def project_files() -> list[str]:
    """The project's files as a user would submit them: tracked or new, never what git ignores
    (the test cache under ``.cache/``, which other tests write while this one copies)."""
    listing = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=PROJECT_ROOT, capture_output=True, text=True, check=True,
    )
    return [name for name in listing.stdout.splitlines() if (PROJECT_ROOT / name).is_file()]


def submitted_copy(root: Path) -> Path:
    """The project as a user might submit it after editing the code: one log line changed."""
    app = root / "app-copy"
    for name in project_files():
        (app / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(PROJECT_ROOT / name, app / name)
    client = app / "zk0" / "federation" / "client.py"
    source = client.read_text()
    assert '"Opened {}' in source
    client.write_text(source.replace('"Opened {}', f'"{MARKER} {{}}'))
    return app


def workers_under(root: Path, module: str = "zk0.deployment.worker") -> list[psutil.Process]:
    """Warm workers (or ``module``'s processes) started by this federation's SuperNodes (their
    working folder is under ``root``)."""
    found = []
    for proc in psutil.process_iter(["cmdline"]):
        try:
            if module in " ".join(proc.info["cmdline"] or []) and Path(proc.cwd()).is_relative_to(root):
                found.append(proc)
        except psutil.Error:
            pass
    return found


def test_bad_supernode_options_fail_in_one_sentence_before_connecting(tmp_path):
    """Nothing starts: each bad value is named in one sentence and the command exits 2."""
    occupied = tmp_path / "a-file"
    occupied.write_text("")
    base = [tool("zk0"), "supernode", "--superlink", "127.0.0.1:1", "--insecure", "--dataset", "synth-so100-pickplace"]
    for extra, expected in [
        (["--cpus", "0"], "zk0: --cpus got 0; expected a number from 1 to "),
        (["--output-dir", str(occupied / "logs")], f"zk0: --output-dir got '{occupied / 'logs'}', where no folder"),
        (["--output-dir", "it's"], "zk0: --output-dir got "),
    ]:
        done = subprocess.run([*base, *extra], capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path)
        assert done.returncode == 2 and done.stderr.startswith(expected), (extra, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr


def test_a_supernode_refuses_a_temporary_folder_others_may_write_in(tmp_path):
    """The warm workers' sockets live in <tmp>/zk0-<uid>: one that others may write in (they could
    have put a socket there) stops `zk0 supernode` in one sentence, before it connects."""
    shared = tmp_path / f"zk0-{os.getuid()}"
    shared.mkdir()
    shared.chmod(0o777)
    command = [
        tool("zk0"),
        "supernode",
        "--superlink",
        "127.0.0.1:1",
        "--insecure",
        "--dataset",
        "synth-so100-pickplace",
    ]
    done = subprocess.run(
        [*command, "--dry-run"], capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path,
        env={**os.environ, "TMPDIR": str(tmp_path)},
    )  # fmt: skip
    assert done.returncode == 2 and done.stderr.startswith(f"zk0: {shared} is not a private folder of this user")
    assert len(done.stderr.strip().splitlines()) == 1 and "TMPDIR" in done.stderr


def test_supernodes_run_the_submitted_code_keep_their_logs_and_stay_warm(federation):
    stranger = federation.supernode("stranger", "synth-so101-reach", "--key", "stranger")
    plaintext = federation.supernode("plaintext", "synth-so101-sorting", "--insecure")
    assert stranger.wait(timeout=120) != 0, "an unregistered key is refused"
    assert "Failed to activate SuperNode" in federation.log("stranger")

    out = federation.root / "outputs-1"
    done = federation.run_app(
        f"num-server-rounds=3 local-steps=2 batch-size=4 eval-batches=1 output-dir='{out}'",
        app=submitted_copy(federation.root),
    )
    run_dir, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1, 2, 3], done.stdout[-3000:]
    assert record["clients"] == {"0": "synth-so100-pickplace", "1": "synth-so100-stacking"}
    assert (run_dir / "models" / "checkpoint_round_3" / "model.safetensors").is_file()
    # Each client's log is on its own machine (its SuperNode's folder), none under the server's run.
    for index, robot in enumerate(ROBOTS):
        log = client_log(federation, robot, run_dir, index)
        assert MARKER in log, "the SuperNode ran the submitted code, not its installed copy"
        assert "Round 3 train" in log and "Round 2 evaluate" in log
        # Its ClientApps were forked from a process that had imported Flower (and forgot its own zk0).
        assert workers_under(federation.root / robot, "zk0.deployment.forkserver"), "the SuperNode's fork server runs"
        assert "fork server exited" not in federation.log(robot)
    # The SuperLink's ServerApp was forked from a process that had imported PyTorch and lerobot.
    assert workers_under(federation.root, "zk0.deployment.forkserver --server"), "the SuperLink's fork server runs"
    assert "fork server exited" not in federation.log("superlink")
    assert not list(run_dir.glob("clients/*/client.log"))
    # The warm worker built each client once; later messages found it built and continued training,
    # in the folder the SuperNodes created first when they registered.
    private = Path(federation.env["TMPDIR"]) / f"zk0-{os.getuid()}"
    assert (private / "supernodes").is_dir() and (private.stat().st_mode & 0o777) == 0o700
    for number in (2, 3):
        for index in ("0", "1"):
            client = record["rounds"][number]["clients"][index]
            train = client["train"]
            assert train["build-s"] == 0.0 and 2 * train["step-time"] <= train["worker-s"] <= train["handler-s"]
            assert client["train"]["lr"] > 0
    assert "evaluate" in record["rounds"][2]["clients"]["0"], "round 2's client evaluation came with round 3"
    deadline = time.monotonic() + 30
    while workers_under(federation.root) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not workers_under(federation.root), "workers exit after the run's last message"

    assert plaintext.poll() is None and "Connection attempt failed" in federation.log("plaintext")
    federation.stop("plaintext")
    nodes = federation.flwr("supernode", "list", "--format", "json").stdout
    assert nodes.count('"online"') == 2, nodes


def test_with_a_time_budget_a_throttled_owner_takes_fewer_steps_and_is_named(federation):
    """robot-2's SuperNode held to a fifth of the CPU from round 2 (zk0.bench.throttle): with local-time-s
    each round lasts about the budget, robot-2 takes fewer steps than robot-1 and is named on the
    console, and the server averages the two with FedNova's normalisation."""
    from zk0.bench.throttle import Throttle

    out = federation.root / "outputs-budget"
    config = "num-server-rounds=3 local-steps=400 local-time-s=2 averaging='fednova' batch-size=4 eval-batches=1"
    config += " eval-frequency=3"
    run = subprocess.Popen(
        [tool("flwr"), "run", str(PROJECT_ROOT), "lan", "--stream", "--run-config", f"{config} output-dir='{out}'"],
        env=federation.env, cwd=PROJECT_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 300
    while not list(out.glob("*/server/round_1.json")):  # round 1 builds the clients: held, that takes minutes
        assert run.poll() is None and time.monotonic() < deadline
        time.sleep(0.2)
    with Throttle(federation.root / "robot-2", share=0.2):
        log, _ = run.communicate(timeout=600)
    run_dir, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1, 2, 3], log[-3000:]
    first = {int(i): c["train"]["local-steps"] for i, c in record["rounds"][1]["clients"].items()}
    assert min(first.values()) > 1, f"starting the warm worker is not the round's work, as the build is not: {first}"
    for r in (2, 3):  # round 1 also builds each client: its first steps are the slowest
        steps = {int(i): c["train"]["local-steps"] for i, c in record["rounds"][r]["clients"].items()}
        assert 1 <= steps[1] < steps[0] / 2 and steps[0] < 400, steps
        line = f"Round {r}/3: 2 clients trained, {steps[1]}-{steps[0]} of 400 steps, stragglers: client 1 ({steps[1]} "
        assert line in log, log[-3000:]
    server_log = (run_dir / "server" / "server.log").read_text()
    assert "local steps; averaged with FedNova" in server_log


def test_a_supernode_whose_disk_is_full_says_so_on_its_console_and_the_run_goes_on(federation):
    """robot-1's output folder on a full filesystem of its own (tmpfs): each train message that must
    keep robot-1's training state fails with zk0's sentence naming that disk, on robot-1's console,
    without a traceback; the server names the client and finishes the run with robot-2."""
    from tests.test_disk import fill, small_disk

    out = federation.root / "outputs-full"
    config = "num-server-rounds=1 local-steps=2 batch-size=4 eval-batches=1 min-train-clients=1"
    before = len(federation.log("robot-1"))
    with small_disk(federation.root / "robot-1" / "outputs", 1) as disk:
        fill(disk)
        done = federation.run_app(f"{config} output-dir='{out}'", timeout=600)
        console = federation.log("robot-1")[before:]
    run_dir, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1], done.stdout[-3000:]
    trained = {i for i, c in record["rounds"][1]["clients"].items() if "train" in c}
    assert trained == {"1"}, "robot-2 trained, robot-1 could not"
    said = [line for line in console.splitlines() if "zk0: Client 0 (synth-so100-pickplace): The disk holding" in line]
    assert len(said) == 1 and "Traceback" not in console, console[-3000:]
    assert all(f"{repr(str(disk))[:-1]}" in line and "is full (0 MB free); free some space" in line for line in said)
    server_log = (run_dir / "server" / "server.log").read_text()
    assert server_log.count("Client 0 (synth-so100-pickplace): The disk holding") == 1, server_log[-3000:]
    assert "no usable update" not in server_log, "a client that said why is not named a second time"


@pytest.mark.allowance(300)
def test_a_run_short_of_owners_ends_with_a_checkpoint_and_resumes(federation):
    """robot-2 stops for good after round 1 of 3 (min-train-clients=2). Whether the SuperLink drops
    it before round 2 samples or after (round 2 then goes on with what arrives), a round finds one
    of the two owners it needs: the console says so once, and after wait-for-owners-s the run ends
    in one sentence with the last round's model kept as a checkpoint (checkpoint-interval would
    keep none yet). Once robot-2 is back, resuming that run folder finishes it with both owners."""
    out = federation.root / "outputs-short"
    config = "num-server-rounds=3 local-steps=2 batch-size=4 eval-batches=1 checkpoint-interval=5"
    run, console = flwr_run(federation, f"{config} wait-for-owners-s=5 output-dir='{out}'")
    wait_for(out, "*/server/round_1.json", run)
    federation.stop("robot-2")
    log = console.finish(timeout=600)
    run_dir, record = history(out)
    done = record["rounds"][-1]["round"]
    assert done in (1, 2), log[-3000:]
    waiting = f"Round {done + 1} waits for owners: 1 of the 2 it needs (min-train-clients=2) connected; the run ends "
    assert log.count(waiting) == 1, log[-3000:]
    ended = (
        f"Round {done + 1} waited 5 s (wait-for-owners-s) with 1 of the 2 owners it needs connected; the run ends here "
        f"with round {done}'s model kept as a checkpoint: ./train.sh --resume {run_dir} (or resume-from='{run_dir}') "
        "continues it once they are back."
    )
    assert ended in log and "Traceback" not in log and run.returncode == 0, log[-3000:]
    assert sorted(p.name for p in (run_dir / "models").glob("checkpoint_round_*")) == [f"checkpoint_round_{done}"]

    federation.supernode("robot-2", ROBOTS["robot-2"], "--key", "robot-2")
    resumed = federation.run_app(f"{config} wait-for-owners-s=300 resume-from='{run_dir}'", timeout=900)
    _, record = history(out)
    assert [r["round"] for r in record["rounds"]] == [0, 1, 2, 3], resumed.stdout[-3000:]
    assert set(record["rounds"][3]["clients"]) == {"0", "1"}, "both owners trained the resumed run's last round"


def wait_for(out: Path, pattern: str, run: subprocess.Popen, timeout: float = 900) -> None:
    """Until ``pattern`` exists under ``out`` (the run still going)."""
    deadline = time.monotonic() + timeout
    while not list(out.glob(pattern)):
        assert run.poll() is None, f"the run ended before {pattern}"
        assert time.monotonic() < deadline, f"no {pattern} after {timeout:.0f} s"
        time.sleep(0.3)


def wait_until(said: Callable[[], str], text: str, count: int = 1, timeout: float = 600) -> None:
    """Until ``said()`` (a log read afresh) holds ``text`` ``count`` times."""
    deadline = time.monotonic() + timeout
    while said().count(text) < count:
        assert time.monotonic() < deadline, f"{text!r} not said {count} time(s) within {timeout:.0f} s"
        time.sleep(0.1)


class Console:
    """A ``flwr run --stream``'s console, read line by line while the run goes on."""

    def __init__(self, run: subprocess.Popen):
        self.run, self.lines = run, []
        self.reader = threading.Thread(target=lambda: self.lines.extend(run.stdout), daemon=True)
        self.reader.start()

    def __call__(self) -> str:
        return "".join(self.lines)

    def finish(self, timeout: float) -> str:
        self.run.wait(timeout=timeout)
        self.reader.join(timeout=30)
        return self()


def flwr_run(fed: LoopbackFederation, config: str) -> tuple[subprocess.Popen, Console]:
    run = subprocess.Popen(
        [tool("flwr"), "run", str(PROJECT_ROOT), "lan", "--stream", "--run-config", config],
        env=fed.env, cwd=PROJECT_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    return run, Console(run)


def supernode_tree(fed: LoopbackFederation, name: str) -> set[int]:
    """The pids of ``name``'s SuperNode and every process under it."""
    parent = psutil.Process(fed.processes[name].pid)
    return {parent.pid, *(child.pid for child in parent.children(recursive=True))}


@pytest.mark.allowance(480)
def test_owners_join_leave_and_come_back_mid_run(tmp_path):
    """Five rounds on the Deployment Engine, min-train-clients=3. In round 2 robot-2 is killed and
    robot-4 stops for good, after each has received round 2's message (their warm workers held
    from round 1's end, so neither can answer it, however fast the machine): each is named once
    when its update does not come, round 2 keeps the global model, and robot-2's warm worker exits
    with its SuperNode. zk0's SuperNodes beat every 10 s, so the server hears they are gone within
    20 s of their last beat (Flower's 30 s beat took 40 to 60 s). Round 3 finds one owner of the
    three it needs and says so on the console; then robot-3 registers for a dataset the run has not
    seen and robot-2 is restarted. robot-3 passes its pre-flight and trains from round 3 on, and
    the round's JSON and report.html say so. robot-2 (its Context.state gone with its process)
    continues from the training state it kept after round 1 and trains from round 3's global model;
    the run finishes without robot-4."""
    robots = {**ROBOTS, "robot-4": "synth-so101-sorting"}
    with loopback_federation(tmp_path / "fed", robots, later=("robot-3",)) as fed:
        out = tmp_path / "outputs"
        config = "num-server-rounds=5 local-steps=2 batch-size=4 eval-batches=1 min-train-clients=3 checkpoint-interval=1"
        run, console = flwr_run(fed, f"{config} wait-for-owners-s=600 output-dir='{out}'")
        wait_for(out, "*/server/round_1.json", run)
        leaving = ("robot-2", "robot-4")
        held = {name: warm_workers_of(supernode_tree(fed, name)) for name in leaving}
        assert all(len(workers) == 1 for workers in held.values()), held
        for workers in held.values():
            workers[0].suspend()
        for name in leaving:  # round 2 sampled them while connected, whenever the SuperLink drops them
            wait_until(lambda name=name: fed.log(name), "Receiving: train message", count=2)
        stopped = datetime.now()
        os.killpg(fed.processes["robot-2"].pid, signal.SIGKILL)
        os.killpg(fed.processes["robot-4"].pid, signal.SIGTERM)
        for workers in held.values():
            workers[0].resume()
        fed.stop("robot-4")
        wait_for(out, "*/server/round_2.json", run)
        deadline = time.monotonic() + 30
        while workers_under(fed.root / "robot-2") and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not workers_under(fed.root / "robot-2"), "a worker exits when its SuperNode is gone"
        waiting = "Round 3 waits for owners: 1 of the 3 it needs (min-train-clients=3) connected; the run ends if "
        wait_until(console, waiting)
        fed.register("robot-3")
        fed.supernode("robot-3", "synth-so101-reach", "--key", "robot-3")
        fed.supernode("robot-2", ROBOTS["robot-2"], "--key", "robot-2")
        log = console.finish(timeout=900)
    assert log.count(waiting) == 1, log[-3000:]
    run_dir, record = history(out)
    rounds = {r["round"]: r for r in record["rounds"]}
    assert list(rounds) == [0, 1, 2, 3, 4, 5], log[-3000:]
    took_part = {i: [n for n, r in rounds.items() if "train" in r["clients"].get(i, {})] for i in ("0", "1", "2", "3")}
    assert took_part == {"0": [1, 2, 3, 4, 5], "1": [1, 3, 4, 5], "2": [1], "3": [3, 4, 5]}, took_part
    assert all("error" not in c.get("train", {}) for r in rounds.values() for c in r["clients"].values())
    assert rounds[3]["joined"] == [3] and "joined" not in rounds[4]
    server_log = (run_dir / "server" / "server.log").read_text()
    for index in (1, 2):
        named = re.findall(rf"^(\S+ \S+) .* no usable update from node \d+ \(client {index}\)", server_log, re.M)
        assert len(named) == 1, server_log
        heard = datetime.strptime(named[0], "%Y-%m-%d %H:%M:%S.%f") - stopped
        assert heard.total_seconds() < 35, f"client {index} named {heard} after it stopped"
    assert "Round 2: 1 valid updates, fewer than min-train-clients=3; the global model is kept." in server_log
    assert "Waiting for nodes to connect: 1 connected (minimum required: 3)" in server_log, "Flower's own line stays"
    restarted = client_log(fed, "robot-2", run_dir, 1)
    assert "Continuing at batch 2 with the optimizer state this client kept after round 1." in restarted
    page = (run_dir / "report.html").read_text().replace(' class="text"', "")
    assert "<td>synth-so101-reach</td><td>3</td>" in page and "<td>synth-so100-stacking</td><td>1</td>" in page


def test_supernodes_without_cpus_divide_the_machine_between_them(tmp_path, monkeypatch):
    """What a default SuperNode gives the processes it starts: its share of the machine's CPUs,
    recomputed before each message from the SuperNodes alive, and PyTorch's threads set to it."""
    import torch

    from zk0.common import machine
    from zk0.deployment.commands import thread_env
    from zk0.federation.client import share_this_machine

    folder, cpus = tmp_path / "supernodes", machine.affinity()
    first = thread_env(None, folder)  # the first SuperNode on this machine has it all
    assert first == {machine.SHARED: str(folder), "OMP_NUM_THREADS": str(cpus), "MKL_NUM_THREADS": str(cpus)}
    machine.register(folder)  # this test process plays the first SuperNode
    assert thread_env(None, folder)["OMP_NUM_THREADS"] == str(max(1, cpus // 2)), "a second one starts with half"
    assert thread_env(1, folder) == {machine.FIXED: "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

    monkeypatch.delenv(machine.FIXED, raising=False)
    monkeypatch.setenv(machine.SHARED, str(folder))
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    threads = torch.get_num_threads()
    try:
        machine.register(folder, other.pid)  # the second SuperNode starts
        assert machine.cpus_now() == max(1, cpus // 2)
        share_this_machine()
        assert torch.get_num_threads() == max(1, cpus // 2)
        other.kill()
        other.wait()
        assert machine.cpus_now() == cpus, "when it stops, the first gets the machine back"
        assert sorted(p.name for p in folder.iterdir()) == [str(os.getpid())], "the stopped one's entry goes"
        monkeypatch.setenv(machine.FIXED, "1")
        assert machine.cpus_now() == 1, "--cpus fixes the share"
    finally:
        other.kill()
        torch.set_num_threads(threads)


def test_supernode_dry_run_shows_the_thread_settings_it_starts_with(tmp_path):
    base = [tool("zk0"), "supernode", "--superlink", "127.0.0.1:1", "--insecure", "--dataset", "synth-so100-pickplace"]
    for extra, expected in ((["--cpus", "1"], "ZK0_CPUS=1 OMP_NUM_THREADS=1"), ([], "ZK0_SUPERNODES=")):
        done = subprocess.run([*base, *extra, "--dry-run"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert done.returncode == 0 and done.stdout.startswith(expected), done.stdout + done.stderr
        assert f"{sys.executable} -m zk0.deployment.supernode --superlink 127.0.0.1:1 --insecure" in done.stdout


def test_zk0s_supernode_polls_instead_of_flowers_hard_coded_waits(monkeypatch):
    """`python -m zk0.deployment.supernode` is Flower's SuperNode whose loop sleeps 0.5 s, not 3 s, between idle
    polls of the SuperLink, and 0.05 s, not 0.5 s, between looks for its ClientApp's reply."""
    from flwr.supernode import start_client_internal as loop

    from zk0 import internals
    from zk0.deployment import supernode
    monkeypatch.setattr(loop, "time", loop.time)  # this process's loop gets Flower's waits back afterwards
    internals.shorten_supernode_waits(supernode.IDLE_POLL_S, supernode.REPLY_POLL_S)
    slept = []
    monkeypatch.setattr(time, "sleep", slept.append)
    for wait in (3, 0.5, 2):
        loop.time.sleep(wait)
    assert slept == [0.5, 0.05, 2] and loop.time.monotonic is time.monotonic
