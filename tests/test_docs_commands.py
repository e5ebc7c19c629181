"""Every command a user would copy from README.md and docs/ runs, at least as a dry run.

Commands are read from the ```bash blocks (with backslash continuations joined). Each is run the
cheapest way that still exercises it: ``zk0 certs`` for real, ``zk0 superlink``/``supernode``
with ``--dry-run`` in a folder holding those certificates (also when the docs run them inside
the Docker image), ``./train.sh`` with ``--print``, ``flwr run``'s run config through
``zk0 check`` and benchmarks' options through their own parsers (both in this process), ``zk0 export``
for real from a run folder made where the example names it,
``lerobot-rollout`` through its own entry point up to where it would load the weights and
connect the robot. A command this test does not know fails
it, so a new documented command cannot go unexercised.
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import shlex
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from unittest import mock

import pytest

from zk0.bench.__main__ import BENCHMARKS
from zk0.cli import main as zk0_main
from zk0.data.registry import PROJECT_ROOT

DOCS = [PROJECT_ROOT / "README.md", *sorted((PROJECT_ROOT / "docs").glob("**/*.md"))]
BIN = Path(sys.executable).parent
# Exercised elsewhere, or not runnable here; each with the reason.
ELSEWHERE = {
    "flwr supernode": "registration and listing run in tests/test_deployment.py",
    "docker build": "built for real with podman by tests/test_container.py (zk0_ensure_image)",
    "docker compose": "the compose federation runs for real, step by step, in tests/test_container.py",
    "mkdir ": "makes the folders the compose federation mounts",
    "./test.sh": "the test command itself",
    "source scripts/setup.sh": "what ./train.sh and ./test.sh run first",
    "cd ": "moves into the clone",
    "git clone": "needs the network",
    "tmux ": "attaching to a detached run",
    "tail -f": "following a log",
    "export ": "sets an environment variable for the commands after it",
    "printf 'ZK0_UID": "writes the compose federation's .env, as tests/test_container.py does",
}


# lerobot-rollout's console-script entry point (lerobot.scripts.lerobot_rollout:main), in this process:
# plugin registration, then lerobot's parser over RolloutConfig, whose __post_init__ reads the policy
# config named by --policy.path. It stops where build_rollout_context would load the weights and
# connect the robot; tests/test_rollout.py runs that part on a zk0 checkpoint with a synthetic SO-101.
def rollout_until_robot(argv: list[str]) -> int:
    """``lerobot-rollout argv`` up to the robot. What its entry point sets for the whole process is
    put back afterwards: the root logger's handlers (lerobot's init_logging replaces them) and the
    signal handlers (its ProcessSignalHandler installs its own)."""
    import lerobot.scripts.lerobot_rollout as cli

    def build_rollout_context(cfg, shutdown_event):
        print(f"{cfg.strategy.type} rollout of {cfg.policy.type} from {cfg.policy.pretrained_path} on {cfg.robot.port}")
        raise SystemExit(0)

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    signals = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)}
    try:
        with (
            mock.patch.object(cli, "build_rollout_context", build_rollout_context),
            mock.patch.object(sys, "argv", ["lerobot-rollout", *argv]),
        ):
            cli.main()
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
        for sig, handler in signals.items():
            signal.signal(sig, handler)
    print("lerobot-rollout ended before it would have connected the robot", file=sys.stderr)
    return 1


def documented_commands() -> list[tuple[str, str]]:
    """(file name, command) for every line of every ```bash block."""
    found = []
    for doc in DOCS:
        for block in re.findall(r"```bash\n(.*?)```", doc.read_text(), re.DOTALL):
            for line in block.replace("\\\n", " ").splitlines():
                line = re.sub(r"\s+#.*$", "", line).strip()
                if line and not line.startswith("#"):
                    found.append((doc.name, line))
    return found


COMMANDS = documented_commands()


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A folder with the certificates the docs' examples name (made as docs/deployment.md makes them)."""
    root = tmp_path_factory.mktemp("docs")
    done = zk0("certs", "--out", "certificates", "--supernode", "robot-alice", "--supernode", "robot-bob", cwd=root)
    assert done.returncode == 0, done.stderr
    return root


def zk0(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``zk0 args``; `zk0 assets` may record the simulator's demonstrations (80 s idle, minutes
    beside the rest of the suite), or wait on another test's recording of them, and `zk0 pretrain`
    builds a policy for each public set."""
    timeout = 900 if args[0] in ("assets", "pretrain") else 120
    command = [str(BIN / "zk0"), *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False)


def checkpoint_config(path: Path) -> None:
    """The config.json of a zk0 checkpoint (SmolVLA, cameras camera1 and camera2, 6 joints) at ``path``.

    It is all lerobot-rollout reads before loading the weights.
    """
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 480, 640))
    SmolVLAConfig(
        input_features={
            "observation.images.camera1": image,
            "observation.images.camera2": image,
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        device="cpu",
        push_to_hub=False,
    ).save_pretrained(path)


def run_folder(path: Path) -> None:
    """The run folder the example names, as a federation leaves it: a checkpoint keeping client 0's
    statistics, and client 0's personal model."""
    from zk0.artifacts.run_folder import PERSONAL, client_dir, save_checkpoint
    from zk0.config import RunConfig
    from zk0.data.loaders import open_metadata
    from zk0.data.registry import load_registry
    from zk0.learning.policy import build_policy

    if (path / "server").is_dir():
        return
    registry = load_registry()
    entry = registry.clients[0]
    bundle = build_policy(RunConfig(device="cpu"), open_metadata(entry), entry, registry.model_cameras())
    (path / "server").mkdir(parents=True)
    save_checkpoint(bundle, path, 3, {f"client_0_{entry.name}": bundle.stats})
    save_checkpoint(bundle, client_dir(path, 0), 3, {}, PERSONAL)


def in_this_process(call, argv: list[str], cwd: Path = PROJECT_ROOT) -> subprocess.CompletedProcess:
    """``call(argv)`` from ``cwd``, its output and exit code as a subprocess's would be: these
    commands need no process of their own, and a fresh one costs each the imports of torch and
    lerobot (17 s a command beside the rest of the suite)."""
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.chdir(cwd), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = call(argv)
    except SystemExit as exited:  # argparse's refusal
        code = exited.code
    return subprocess.CompletedProcess(argv, code or 0, out.getvalue(), err.getvalue())


def pretrained(tokens: list[str], workspace: Path) -> subprocess.CompletedProcess:
    """The documented `zk0 pretrain`, for real in the workspace but for 2 steps (the example's
    count is a study's; each step is the federation's own), once: the `flwr run` after it
    federates from its folder."""
    tokens = list(tokens)
    if (workspace / tokens[tokens.index("--out") + 1]).exists():
        return subprocess.CompletedProcess(tokens, 0, "", "")
    tokens[tokens.index("--steps") + 1] = "2"
    made = zk0("assets", "--run-config", tokens[tokens.index("--run-config") + 1], cwd=workspace)
    return made if made.returncode else zk0(*tokens[1:], cwd=workspace)


def parse_benchmark(argv: list[str]) -> int:
    """A benchmark's documented options through its own parser: a misspelt option, value or
    benchmark fails as it would for the user (each benchmark runs in its own tests)."""
    assert argv[0] in BENCHMARKS, f"python -m zk0.bench has no benchmark {argv[0]!r}"
    BENCHMARKS[argv[0]].build_parser().parse_args(argv[1:])
    return 0


def inner_command(tokens: list[str]) -> list[str]:
    """What ``docker run ... zk0 <command>`` runs inside the image."""
    image = next(i for i, token in enumerate(tokens) if token == "zk0" and i + 1 < len(tokens))
    return tokens[image + 1 :]


def exercise(tokens: list[str], workspace: Path) -> subprocess.CompletedProcess:
    if tokens[0] == "docker":
        return exercise(inner_command(tokens), workspace)
    if tokens[:2] == ["zk0", "certs"]:
        return zk0(*tokens[1:], cwd=workspace)
    if tokens[0] == "zk0" and tokens[1] in {"superlink", "supernode"}:
        return zk0(*tokens[1:], "--dry-run", cwd=workspace)
    if tokens[:2] == ["zk0", "check"]:
        return in_this_process(zk0_main, tokens[1:])
    if tokens[:2] == ["zk0", "export"]:  # for real, from a run folder made where the example names it
        run_folder(workspace / tokens[2])
        return in_this_process(zk0_main, tokens[1:], cwd=workspace)
    if tokens[:2] == ["zk0", "pretrain"]:
        return pretrained(tokens, workspace)
    if tokens[0] == "zk0":
        return zk0(*tokens[1:], cwd=workspace)
    if tokens[0] == "./train.sh":
        # From the project folder for --docker, whose container sees the project's outputs/ only.
        cwd = PROJECT_ROOT if "--docker" in tokens else workspace
        command = [str(PROJECT_ROOT / "train.sh"), *tokens[1:], "--print"]
        if "--resume" not in tokens:
            return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300, check=False)
        (cwd / "outputs").mkdir(exist_ok=True)
        run = Path(tempfile.mkdtemp(dir=cwd / "outputs"))
        command[command.index("--resume") + 1] = str(run)  # the example run folder, as an interrupted run leaves it
        try:
            return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300, check=False)
        finally:
            run.rmdir()
    if tokens[:2] == ["flwr", "run"]:
        config = tokens[tokens.index("--run-config") + 1] if "--run-config" in tokens else ""
        if "registry=" in config:  # its owners' datasets, made by the `zk0 assets` the docs run first
            made = zk0("assets", "--run-config", config, cwd=PROJECT_ROOT)
            if made.returncode:
                return made
        option = ["--preset", str(PROJECT_ROOT / config)] if config.endswith(".toml") else ["--run-config", config]
        base = re.search(r"model='(outputs/[^']+)'", config)
        if base:  # the model the docs' `zk0 pretrain` makes, checked where it made it
            (pretrain,) = [shlex.split(c) for _, c in COMMANDS if c.startswith("zk0 pretrain") and base[1] in c]
            made = pretrained(pretrain, workspace)
            return made if made.returncode else in_this_process(zk0_main, ["check", *option], cwd=workspace)
        return in_this_process(zk0_main, ["check", *option])
    if tokens[0] == "lerobot-rollout":
        policy = next(token.split("=", 1)[1] for token in tokens if token.startswith("--policy.path="))
        checkpoint_config(workspace / policy)  # the run folder's checkpoint the example names
        return in_this_process(rollout_until_robot, tokens[1:], cwd=workspace)
    if tokens[:2] == ["MUJOCO_GL=egl", "lerobot-eval"]:  # run for real in tests/test_sim.py
        command = [str(BIN / "lerobot-eval"), *tokens[2:], "--help"]
        done = subprocess.run(command, cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120, check=False)
        if "--env.conditions" not in done.stdout:  # only zk0's env has it: lerobot found the plugin
            return subprocess.CompletedProcess(command, 1, done.stdout, "lerobot-eval does not know zk0_so101")
        return done
    if tokens[:3] == ["python", "-m", "zk0.bench"]:
        return in_this_process(parse_benchmark, tokens[3:])
    raise AssertionError(f"No way to exercise {shlex.join(tokens)!r}; teach tests/test_docs_commands.py one.")


def marked(doc: str, command: str):
    """`zk0 assets` of a simulated registry records its demonstrations, and of many owners generates
    sixteen datasets (as does checking a run on them, which makes them first), and `lerobot-eval`
    is a process of its own importing lerobot: the full suite's."""
    makes_assets = command.startswith(("zk0 assets", "flwr run", "zk0 pretrain"))
    slow = makes_assets and ("sim" in command or "owners" in command or "public" in command)
    slow = slow or "lerobot-eval" in command
    return pytest.param(doc, command, marks=[pytest.mark.slow] if slow else [], id=f"{doc}:{command[:60]}")


@pytest.mark.parametrize(("doc", "command"), [marked(d, c) for d, c in COMMANDS])
def test_documented_command_runs(doc, command, workspace):
    if any(command.startswith(prefix) for prefix in ELSEWHERE):
        pytest.skip(next(reason for prefix, reason in ELSEWHERE.items() if command.startswith(prefix)))
    done = exercise(shlex.split(command), workspace)
    assert done.returncode == 0, f"{doc}: `{command}` exited {done.returncode}: {done.stderr[-1500:]}"


def test_the_docs_show_the_deployment_commands():
    """The scan finds what matters (a broken regex must not turn this file into a no-op)."""
    text = " ".join(command for _, command in COMMANDS)
    for expected in (
        "zk0 certs",
        "zk0 superlink",
        "zk0 supernode",
        "./train.sh",
        "flwr run",
        "docker run",
        "lerobot-rollout",
    ):
        assert expected in text, expected


def heading_anchors(path: Path) -> set[str]:
    """GitHub's anchors for a page's headings: lower case, punctuation dropped, spaces to hyphens."""
    headings = re.findall(r"^#+ (.+)$", path.read_text(), re.MULTILINE)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def test_every_link_between_the_docs_lands_on_a_file_and_heading_that_exist():
    broken = []
    for doc in DOCS:
        for target, anchor in re.findall(r"\]\((?!https?:|mailto:)([^)#\s]*)(?:#([^)\s]+))?\)", doc.read_text()):
            path = (doc.parent / target).resolve() if target else doc
            if not path.exists() or (anchor and path.suffix == ".md" and anchor not in heading_anchors(path)):
                broken.append(f"{doc.relative_to(PROJECT_ROOT)} -> {target}#{anchor}")
    assert not broken, broken


def test_the_results_page_stays_a_results_page_and_links_every_investigation():
    learning = PROJECT_ROOT / "docs" / "learning.md"
    assert len(learning.read_text().splitlines()) <= 250, "results first: investigations go to docs/notes/"
    linked = set(re.findall(r"\]\(notes/([^)]+\.md)\)", learning.read_text()))
    assert linked == {p.name for p in (PROJECT_ROOT / "docs" / "notes").glob("*.md")}
