"""train.sh's flags and the Dockerfile: documented, linted, and consistent with each other."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

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
    for line in runs:
        for mount in re.findall(r"-v \S+:(/\S+?)(?::ro)?(?=\s)", line):
            assert mount.startswith(("/workspace/", "/home/zk0/.cache")), line


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
