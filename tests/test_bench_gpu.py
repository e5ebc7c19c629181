"""``python -m zk0.bench gpu`` on a short lease: stages in the order named, skipped by name for time."""

import json

from zk0.bench import gpu


def test_a_stage_without_the_time_to_run_is_skipped_by_name(tmp_path, capsys):
    out = tmp_path / "gpu.json"
    code = gpu.main(["--model", "tiny", "--stages", "exchange,step-eager", "--time-limit", "30", "--json", str(out)])
    figures = json.loads(out.read_text())
    assert code == 0
    assert figures["skipped"] == ["exchange", "step-eager"]
    assert "exchange" not in figures and "step-eager" not in figures
    assert "skipped for time: exchange, step-eager" in capsys.readouterr().out


def test_stages_run_in_the_order_named_with_memory_at_two_batches():
    args = gpu.build_parser().parse_args(["--batch-size", "32", "--stages", "memory,step-compiled"])
    runs = gpu.stage_runs(args, gpu.stage_list(gpu.build_parser(), args.stages))
    assert [key for key, *_ in runs] == ["memory-8", "memory-32", "step-compiled"]
    assert "--compile" in runs[-1][2]


def test_the_split_between_two_points_gives_the_batch_that_fills_the_budget():
    assert gpu.largest_batch((16, 5.0), (64, 11.0), 24.0) == 168
