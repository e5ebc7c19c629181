"""Every command's --help exits 0 with usage; a bad argument exits 2 with one sentence."""

from __future__ import annotations

import pytest

from zk0.bench.__main__ import BENCHMARKS
from zk0.bench.__main__ import main as bench
from zk0.cli import build_parser
from zk0.cli import main as zk0


def exit_code(call, argv: list[str]) -> int:
    try:
        return call(argv)
    except SystemExit as done:  # argparse's --help and errors
        return done.code


COMMANDS = ["assets", "check", "pretrain", "certs", "superlink", "supernode", "export"]
BENCHES = (
    "learning, study, robust, robustness, exchange, step, round, memory, deployment, gpu, sim, inputs, sim-learning, "
    "hetero, scale, owners, soak, privacy, secagg, container, policies"
)


def test_the_benchmark_list_is_zk0s():
    assert ", ".join(BENCHMARKS) == BENCHES


def test_the_command_list_is_zk0s():
    assert "{" + ",".join(COMMANDS) + "}" in build_parser().format_usage()


@pytest.mark.parametrize("command", [[], *([name] for name in COMMANDS)])
def test_zk0_help_exits_0_with_usage(command, capsys):
    assert exit_code(zk0, [*command, "--help"]) == 0
    assert capsys.readouterr().out.startswith(f"usage: {' '.join(['zk0', *command])}")


@pytest.mark.parametrize("benchmark", [None, *BENCHMARKS])
def test_bench_help_exits_0_with_usage(benchmark, capsys):
    assert exit_code(bench, [benchmark, "--help"] if benchmark else ["--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: python -m zk0.bench {benchmark or '<benchmark>'}")
    if benchmark is None:
        assert all(f"  {name} " in out for name in BENCHMARKS)


@pytest.mark.parametrize(
    ("call", "argv", "sentence"),
    [
        (
            bench,
            ["steps"],
            f"python -m zk0.bench: got 'steps'; expected one of {BENCHES} (see --help).",
        ),
        (bench, [], f"python -m zk0.bench: got nothing; expected one of {BENCHES} (see --help)."),
        (
            bench,
            ["step", "--bogus"],
            "python -m zk0.bench step: unrecognized arguments: --bogus; see python -m zk0.bench step --help.",
        ),
        (
            zk0,
            ["supernode", "--superlink", "h:1"],
            "zk0 supernode: the following arguments are required: --dataset; see zk0 supernode --help.",
        ),
        (zk0, ["assets", "--seed", "x"], "zk0 assets: argument --seed: invalid int value: 'x'; see zk0 assets --help."),
        (
            bench,
            ["exchange", "--peft", "lora", "--lora-rank", "0"],
            "python -m zk0.bench exchange: argument --lora-rank: got '0'; expected int > 0; "
            "see python -m zk0.bench exchange --help.",
        ),
        (
            bench,
            ["step", "--policy", "act", "--peft", "lora"],
            "python -m zk0.bench step: Run-config key 'peft' = 'lora' adapts SmolVLA, and policy='act' trains in "
            "full; expected peft='none'.",
        ),
        (
            bench,
            ["exchange", "--policy", "act", "--peft", "lora"],
            "python -m zk0.bench exchange: --peft lora adapts SmolVLA, and --policy is act; expected --peft none; "
            "see python -m zk0.bench exchange --help.",
        ),
        (
            bench,
            ["study", "--rounds", "0"],
            "python -m zk0.bench study: argument --rounds: got '0'; expected int > 0; "
            "see python -m zk0.bench study --help.",
        ),
        (
            bench,
            ["study", "--clients", "5"],
            "python -m zk0.bench study: --clients got 5; the mild setting has 4 client datasets; "
            "see python -m zk0.bench study --help.",
        ),
        (
            bench,
            ["study", "--seeds", "42", "42"],
            "python -m zk0.bench study: --seeds got 42 42; expected different seeds, each 0 or more; "
            "see python -m zk0.bench study --help.",
        ),
        (
            bench,
            ["hetero", "--share", "2"],
            "python -m zk0.bench hetero: --share got 2.0; expected a share of the CPU in (0, 1]; "
            "see python -m zk0.bench hetero --help.",
        ),
        (
            bench,
            ["hetero", "--slow", "4"],
            "python -m zk0.bench hetero: --slow got 4; expected fewer than --clients (4): someone must be fast; "
            "see python -m zk0.bench hetero --help.",
        ),
        (
            bench,
            ["soak", "--rounds", "10"],
            "python -m zk0.bench soak: --from-round got 10; expected a round before the last (10); "
            "see python -m zk0.bench soak --help.",
        ),
        (
            bench,
            ["scale", "--owners", "1", "16"],
            "python -m zk0.bench scale: --owners got 1; expected 2 or more owners in each federation; "
            "see python -m zk0.bench scale --help.",
        ),
        (
            bench,
            ["privacy", "--registry", "/nowhere/registry.toml"],
            "python -m zk0.bench privacy: --registry: Registry file '/nowhere/registry.toml' cannot be read "
            "(No such file or directory); see python -m zk0.bench privacy --help.",
        ),
        (
            bench,
            ["gpu", "--stages", "step-eager,compiled"],
            "python -m zk0.bench gpu: --stages got 'step-eager,compiled'; expected a comma-separated list of "
            "step-eager, step-compiled, memory, deployment, exchange; see python -m zk0.bench gpu --help.",
        ),
        (
            bench,
            ["learning", "--peft", "lora", "--lora-lr", "fast"],
            "python -m zk0.bench learning: argument --lora-lr: got 'fast'; expected float > 0; "
            "see python -m zk0.bench learning --help.",
        ),
    ],
)
def test_a_bad_argument_exits_2_with_one_sentence(call, argv, sentence, capsys):
    assert exit_code(call, argv) == 2
    assert capsys.readouterr().err == sentence + "\n"


@pytest.mark.e2e
def test_a_killed_benchmark_stops_the_federation_it_started(tmp_path):
    """`kill` (SIGTERM) to a benchmark while its federation trains: the benchmark exits 143 and
    every process it started (`flwr run`, the SuperLink, the ServerApp, Ray's) is gone soon after."""
    import signal
    import subprocess
    import sys
    import time

    import psutil

    command = [sys.executable, "-m", "zk0.bench", "round", "--local-steps", "100000", "--output-dir", str(tmp_path)]
    benchmark = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300

    def started() -> list[psutil.Process]:
        tree = psutil.Process(benchmark.pid).children(recursive=True)
        names = []
        for process in tree:
            try:
                names.append(process.name())
            except psutil.NoSuchProcess:
                pass
        return tree if any(name.startswith("ray::ClientApp") for name in names) else []

    tree: list[psutil.Process] = []
    try:
        while not (tree := started()):
            assert benchmark.poll() is None and time.monotonic() < deadline, benchmark.stderr.read()[-3000:]
            time.sleep(0.5)
        benchmark.send_signal(signal.SIGTERM)
        assert benchmark.wait(timeout=120) == 128 + signal.SIGTERM
        _, alive = psutil.wait_procs(tree, timeout=30)
        assert not alive, [" ".join(p.cmdline()) for p in alive if p.is_running()]
    finally:  # a failure leaves no federation training on beside the rest of the suite
        for process in [psutil.Process(benchmark.pid), *tree] if benchmark.poll() is None else tree:
            try:
                process.kill()
            except psutil.NoSuchProcess:
                pass
