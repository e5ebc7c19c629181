"""train.sh's flags and the Dockerfile: documented, linted, and consistent with each other."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from zk0.data.registry import PROJECT_ROOT

TRAIN = str(PROJECT_ROOT / "train.sh")


def train(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([TRAIN, *args], capture_output=True, text=True, timeout=120, check=False)


def test_help_documents_every_flag_the_script_accepts():
    script = Path(TRAIN).read_text()
    flags = set(re.findall(r"^\s+(-{1,2}[\w-]+)(?: \| (-{1,2}[\w-]+))?\)", script, re.MULTILINE))
    accepted = {flag for pair in flags for flag in pair if flag}
    assert {"--docker", "--detached", "--preset", "--resume", "--mode", "--run-config"} <= accepted
    usage = train("--help").stdout
    for flag in accepted:
        assert flag in usage, flag


def test_unknown_flag_fails_in_one_sentence():
    done = train("--turbo")
    assert done.returncode == 2
    assert done.stderr.strip() == "train.sh: unknown option '--turbo'; see ./train.sh --help."


def train_in(engine: str, *args: str) -> list[str]:
    """The command ``./train.sh --docker --print`` shows with ``engine`` chosen."""
    done = subprocess.run(
        [TRAIN, "--docker", "--print", *args], env={**os.environ, "ZK0_ENGINE": engine},
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_docker_runs_the_same_command_in_the_image_with_outputs_mounted():
    command = train_in("docker", "-m", "gpu-serial", "-r", "local-steps=3")
    assert command[:2] == ["docker", "run"] and "--gpus" in command
    mount = command[command.index("-v") + 1]
    assert mount == f"{PROJECT_ROOT}/outputs:/workspace/outputs"
    assert command[command.index("--user") + 1] == f"{os.getuid()}:{os.getgid()}", "outputs/ stays the host user's"
    assert "OMP_NUM_THREADS" in command, "the thread limit set here (tests/conftest.py) reaches the container"
    assert command[-6:] == ["zk0", "./train.sh", "-m", "gpu-serial", "-r", "local-steps=3"]
    dockerfile = (PROJECT_ROOT / "Dockerfile").read_text()
    assert "WORKDIR /workspace" in dockerfile and 'VOLUME ["/home/zk0/.cache"]' in dockerfile
    assert "--gpus" not in train_in("docker"), "a CPU run asks for no GPU"


def test_podman_runs_the_same_command_with_its_own_gpu_flag():
    command = train_in("podman", "-m", "gpu")
    assert command[:2] == ["podman", "run"] and "--gpus" not in command
    assert command[command.index("--device") + 1] == "nvidia.com/gpu=all", "podman passes GPUs through CDI"


def test_docker_resumes_a_run_by_its_place_under_outputs(tmp_path):
    run = PROJECT_ROOT / "outputs" / f"resume-test-{os.getpid()}"
    run.mkdir(parents=True)
    try:
        command = train_in("docker", "--resume", str(run))
        assert command[-3:] == ["./train.sh", "--resume", f"outputs/{run.name}"], "the container's path, not the host's"
        done = train("--docker", "--print", "--resume", str(tmp_path))
        assert done.returncode == 2 and done.stderr.strip() == (
            f"train.sh: --docker resumes runs under {PROJECT_ROOT}/outputs/ only (that folder is what the "
            f"container sees); got '{tmp_path}'."
        )
    finally:
        run.rmdir()


def test_an_unknown_engine_is_one_sentence():
    done = subprocess.run(
        [TRAIN, "--docker", "--print"], env={**os.environ, "ZK0_ENGINE": "lxc"},
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and done.stderr.strip() == "train.sh: ZK0_ENGINE is 'lxc'; expected docker or podman."


def test_docker_detached_is_a_named_container_with_its_log_and_stop_commands():
    command = train_in("podman", "--detached", "-r", "num-server-rounds=2")
    assert command[:4] == ["podman", "run", "-d", "--name"] and command[4].startswith("zk0-")
    assert command[-3:] == ["./train.sh", "-r", "num-server-rounds=2"]


def test_a_missing_engine_is_one_sentence(tmp_path):
    """With neither Docker nor podman on PATH, --docker says what to install, before anything runs."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("bash", "dirname", "date", "id", "mkdir", "cat"):
        (bin_dir / tool).symlink_to(shutil.which(tool))
    done = subprocess.run(
        [str(PROJECT_ROOT / "train.sh"), "--docker"],
        env={"PATH": str(bin_dir), "HOME": str(tmp_path)}, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip() == (
        "train.sh: --docker needs Docker or podman; install one (e.g. apt-get install podman) or run without --docker."
    )
    assert not (tmp_path / "outputs").exists()


def test_detached_runs_in_a_named_tmux_session():
    done = train("--detached", "--print", "-r", "num-server-rounds=2")
    assert re.match(r"tmux new-session -d -s zk0-\d{8}-\d{6} ", done.stdout)
    assert "train.sh" in done.stdout and "num-server-rounds=2" in done.stdout


def test_dockerfile_passes_hadolint():
    hadolint = Path(sys.executable).with_name("hadolint")
    done = subprocess.run([str(hadolint), "Dockerfile"], cwd=PROJECT_ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout + done.stderr


def test_readme_docker_commands_match_the_image():
    readme = (PROJECT_ROOT / "README.md").read_text()
    runs = [line for line in readme.splitlines() if line.startswith("docker run")]
    assert runs, "the README shows how to run the image"
    mounts = {m.strip('"') for line in runs for m in re.findall(r"-v \S+:(/\S+?)(?::ro)?(?=\s)", line)}
    assert mounts == {"/workspace/outputs", "/home/zk0/.cache"}, mounts


def test_flower_packs_the_app_without_walking_the_linked_venv(tmp_path):
    """.venv links outside the project: Flower's app packing walks every file it can reach under it."""
    from flwr.cli.utils import collect_files

    env = {**os.environ, "ZK0_CACHE": str(tmp_path / "cache")}
    home = subprocess.run(
        ["bash", "-c", "source scripts/setup.sh && zk0_venv_home"],
        cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    assert Path(home).parent == tmp_path / "cache" / "venvs"
    (Path(home) / "lib").mkdir(parents=True)
    (Path(home) / "lib" / "module.py").write_text("")
    app = tmp_path / "app"
    app.mkdir()
    (app / "pyproject.toml").write_text("")
    (app / ".venv").symlink_to(home)
    assert set(collect_files(app)) == {"pyproject.toml"}


def own_flower(tmp_path: Path) -> dict[str, str]:
    """An environment whose `flwr run` starts a SuperLink of its own (own home, own ports)."""
    from zk0.deployment.simulation import free_port

    return {
        **os.environ,
        "FLWR_HOME": str(tmp_path / "flwr"),
        "FLWR_LOCAL_SUPERLINK_HTTP_API_PORT": str(free_port()),
        "FLWR_LOCAL_CONTROL_API_PORT": str(free_port()),
    }


def check_console(printed: str, run_dir: Path, rounds_run: int) -> None:
    """train.sh's console is for a person: at most 25 lines for a round and one per further round,
    zk0's lines only (no traceback, progress bar or Flower metric dump), and every figure the header,
    the round lines and the summary print is the one in the run's JSON."""
    import json

    lines = printed.splitlines()
    assert len(lines) <= 25 + rounds_run - 1, printed
    assert all(line.startswith("[zk0] ") or line.startswith("  ./train.sh") for line in lines), printed
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    config = json.loads((run_dir / "server" / "run_config.json").read_text())
    rounds = {r["round"]: r for r in history["rounds"]}
    last = max(rounds)
    clients = ", ".join(f"{i} {name}" for i, name in history["clients"].items())
    assert f"[zk0] {len(history['clients'])} clients: {clients}; the server evaluates on " in printed
    tensors = rounds[last]["global-arrays"]["tensors"]
    assert re.search(rf"\[zk0\] Model: {config['model']} SmolVLA \([\d,]+ trainable parameters in {tensors} tensors\)", printed)
    steps = f"{config['num-server-rounds']} round{'s' * (config['num-server-rounds'] != 1)} x {config['local-steps']}"
    assert f"[zk0] {steps} local steps (batch {config['batch-size']})" in printed
    if 0 in rounds and f"[zk0] Writing to {run_dir}" in printed:
        assert f"Round 0 (the starting model): server action MSE {rounds[0]['server-evaluate']['action-mse']:.4g}" in printed
    for line in lines:
        shown = re.match(r"\[zk0\] Round (\d+)/\d+: (\d+) clients? trained, train loss ([\d.e+-]+), server action MSE ([\d.e+-]+)", line)
        if shown:
            record = rounds[int(shown[1])]
            trained = sum("error" not in c.get("train", {"error": ""}) for c in record["clients"].values())
            assert shown.groups()[1:] == (
                str(trained),
                f"{record['aggregate-train']['train-loss']:.4g}",
                f"{record['server-evaluate']['action-mse']:.4g}",
            ), line
    assert len([line for line in lines if re.match(r"\[zk0\] Round \d+/", line)]) == rounds_run
    best = rounds[last]["best"]
    assert re.search(rf"\[zk0\] Done in \d+ s: models/best is round {best['round']} \(server action MSE {best['action-mse']:.4g}", printed)
    assert f"[zk0] Report: {run_dir}/report.html" in printed and (run_dir / "report.html").is_file()
    assert (run_dir / "console.log").is_file(), "what flwr run printed is kept with the run"


@pytest.mark.e2e
def test_the_quick_runs_console_reads_in_one_glance(tmp_path):
    """The README's ./train.sh (1 round, 2 steps), with its outputs in a folder of the test's; its
    report's figures are the JSON's."""
    import json

    out = tmp_path / "outputs"
    done = subprocess.run(
        [TRAIN, "-r", f"output-dir='{out}'"],
        env=own_flower(tmp_path),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    printed = done.stdout + done.stderr
    assert done.returncode == 0, printed[-3000:]
    (run_dir,) = out.iterdir()
    check_console(printed, run_dir, rounds_run=1)
    assert printed.splitlines()[-1] == f"[zk0] Outputs: {run_dir}"
    from tests.test_report import Tables

    page = Tables()
    page.feed((run_dir / "report.html").read_text())
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    header, *rows = page.tables["rounds"]
    column = [c[0] for c in header].index("server action MSE")
    assert [float(row[column][1]) for row in rows] == [r["server-evaluate"]["action-mse"] for r in history["rounds"]]
    log = (run_dir / "server" / "server.log").read_text()
    assert "Aggregated ClientApp-side Train Metrics" in log and "Starting ValidatingStrategy strategy" in log, (
        "Flower's own lines are in the log, not lost"
    )


@pytest.mark.allowance(240)
@pytest.mark.e2e
def test_ctrl_c_stops_the_run_at_once_and_prints_the_command_that_continues_it(tmp_path):
    """SIGINT to ./train.sh after round 1 of 6 short rounds (several fit in Flower's 5 s exit): no
    later round is written, no file of the run changes once it says it stopped, no process of the run
    is left, and the printed --resume command finishes the run."""
    import json
    import shlex
    import signal
    import time

    import psutil

    from zk0.deployment.simulation import superlink_tree

    out = tmp_path / "outputs"
    env = own_flower(tmp_path) | {"COLUMNS": "80"}  # a narrow terminal: ps cuts command lines to it
    overrides = (
        f"num-server-rounds=6 local-steps=1 batch-size=4 checkpoint-interval=1 eval-batches=1 output-dir='{out}'"
    )
    # As from a terminal: its own process group, which Ctrl-C signals whole (train.sh, flwr run and
    # what Flower starts in it); and SIGINT at its default, since a shell that inherits it ignored
    # (pytest started in the background by a non-interactive shell, as `cmd &` does) cannot trap it.
    first = subprocess.Popen(
        [TRAIN, "-r", overrides],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        process_group=0,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 600
    while not list(out.glob("*/models/checkpoint_round_1")):
        assert first.poll() is None and time.monotonic() < deadline, first.stdout.read()[-3000:]
        time.sleep(0.05)
    run_processes = superlink_tree(env)
    assert run_processes, "the run's SuperLink and simulation are running"
    (run_dir,) = out.iterdir()
    written = max(int(p.stem.split("_")[1]) for p in (run_dir / "server").glob("round_*.json"))
    os.killpg(first.pid, signal.SIGINT)
    printed, _ = first.communicate(timeout=180)
    assert first.returncode == 130, printed[-3000:]
    files = {p: p.stat().st_mtime_ns for p in run_dir.rglob("*")}
    time.sleep(3)
    assert {p: p.stat().st_mtime_ns for p in run_dir.rglob("*")} == files, "nothing changes once it has stopped"
    rounds = sorted(int(p.stem.split("_")[1]) for p in (run_dir / "server").glob("round_*.json"))
    assert rounds[-1] == written, f"round {written} was written when stopped; the server went on to {rounds}"
    assert not [p.pid for p in run_processes if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert f"[zk0] Stopped in round {rounds[-1] + 1} (rounds up to {rounds[-1]} are written)" in printed
    assert f"Last complete checkpoint: {run_dir}/models/checkpoint_round_" in printed
    (command,) = [line.strip() for line in printed.splitlines() if line.startswith("  ./train.sh")]
    assert shlex.split(command) == ["./train.sh", "-r", overrides, "--resume", str(run_dir)]

    second = subprocess.run(
        shlex.split(command), cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=600, check=False
    )
    assert second.returncode == 0, second.stderr[-3000:]
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    assert [r["round"] for r in history["rounds"]] == list(range(7))
    assert (run_dir / "models" / "checkpoint_round_6" / "model.safetensors").is_file()
    resumed_from = int(re.search(r"after round (\d+)", second.stdout + second.stderr)[1])
    check_console(second.stdout + second.stderr, run_dir, rounds_run=6 - resumed_from)
