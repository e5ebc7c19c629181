"""train.sh's flags and the Dockerfile: documented, linted, and consistent with each other."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from zk0.registry import PROJECT_ROOT

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


def test_docker_runs_the_same_command_in_the_image_with_outputs_mounted():
    done = train("--docker", "--print", "-m", "gpu-serial", "-r", "local-steps=3")
    command = done.stdout.split()
    assert command[:2] == ["docker", "run"] and "--gpus" in command
    mount = command[command.index("-v") + 1]
    assert mount == f"{PROJECT_ROOT}/outputs:/workspace/outputs"
    assert command[-6:] == ["zk0", "./train.sh", "-m", "gpu-serial", "-r", "local-steps=3"]
    dockerfile = (PROJECT_ROOT / "Dockerfile").read_text()
    assert "WORKDIR /workspace" in dockerfile and 'VOLUME ["/home/zk0/.cache"]' in dockerfile
    assert "--gpus" not in train("--docker", "--print").stdout, "a CPU run asks for no GPU"


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


@pytest.mark.e2e
def test_ctrl_c_stops_the_run_and_prints_the_command_that_continues_it(tmp_path):
    """SIGINT to ./train.sh during round 2 of 4: no later round, no process of the run left, and
    the printed --resume command finishes the run."""
    import json
    import shlex
    import signal
    import time

    import psutil

    from zk0.simulation import free_port, superlink_tree

    out = tmp_path / "outputs"
    env = {
        **os.environ,
        "FLWR_HOME": str(tmp_path / "flwr"),
        "FLWR_LOCAL_SUPERLINK_HTTP_API_PORT": str(free_port()),
        "FLWR_LOCAL_CONTROL_API_PORT": str(free_port()),
    }
    overrides = (
        f"num-server-rounds=4 local-steps=2 batch-size=4 checkpoint-interval=1 eval-batches=1 output-dir='{out}'"
    )
    # As from a terminal: a shell that inherits an ignored SIGINT (pytest started in the background
    # by a non-interactive shell, as `cmd &` does) cannot trap it, so the test puts the default back.
    first = subprocess.Popen(
        [TRAIN, "-r", overrides],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 600
    while not list(out.glob("*/models/checkpoint_round_1")):
        assert first.poll() is None and time.monotonic() < deadline, first.stdout.read()[-3000:]
        time.sleep(0.2)
    run_processes = superlink_tree(env)
    assert run_processes, "the run's SuperLink and simulation are running"
    first.send_signal(signal.SIGINT)
    printed, _ = first.communicate(timeout=180)
    assert first.returncode == 130, printed[-3000:]
    time.sleep(3)
    (run_dir,) = out.iterdir()
    assert not (run_dir / "server" / "round_3.json").exists(), "no round after the interrupted one"
    assert not [p.pid for p in run_processes if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert f"Last complete checkpoint: {run_dir}/models/checkpoint_round_" in printed
    (command,) = [line.strip() for line in printed.splitlines() if line.startswith("  ./train.sh")]
    assert shlex.split(command) == ["./train.sh", "-r", overrides, "--resume", str(run_dir)]

    second = subprocess.run(
        shlex.split(command), cwd=PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=600, check=False
    )
    assert second.returncode == 0, second.stderr[-3000:]
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    assert [r["round"] for r in history["rounds"]] == [0, 1, 2, 3, 4]
    assert (run_dir / "models" / "checkpoint_round_4" / "model.safetensors").is_file()
