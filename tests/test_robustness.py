"""python -m zk0.bench robustness: every model with and without lerobot's transforms, in and outside the span."""

from __future__ import annotations

import json

import pytest

from zk0.bench.robustness import build_parser, condition, span_of, table, targets


def test_conditions_are_named_from_the_server_or_the_owner_and_compared_with_their_own_span():
    assert condition("dim-0", "sim-so101-eval-cube") == "sim-so101-outside-dim-0-cube"
    assert condition("bright-1", "sim-so101-far-left-cube") == "sim-so101-far-left-outside-bright-1-cube"
    assert [span_of(c) for c in ("server", "dim-0", "client 2", "client 2 dim-0")] == [
        "server", "server", "client 2", "client 2",
    ]  # fmt: skip


def test_the_table_pools_seeds_pairs_with_and_without_and_judges_the_targets():
    """Rates over every seed's episodes, each against its own span's rate, McNemar on the same
    episodes; the lighting target fails when one lighting condition falls under 0.8x."""

    def rolled(server: list[int], dim: list[int], table_: list[int]) -> dict:
        def rates(o):
            return {"outcomes": o, "success-rate": sum(o) / len(o)}

        return {"global": {"server": rates(server), "dim-0": rates(dim), "table-0": rates(table_)},
                "personal 0": {"client 0": rates(server), "client 0 dim-0": rates(dim)}}  # fmt: skip

    seeds = {
        s: {"off": rolled([1, 1, 1, 1], [0, 0, 0, 0], [1, 0, 0, 0]), "on": rolled([1, 1, 1, 1], [1, 1, 1, 0], [0] * 4)}
        for s in (1, 2)
    }
    rows = table(seeds, build_parser().parse_args([]))
    dim_on = next(r for r in rows if (r["model"], r["column"], r["transforms"]) == ("global", "dim-0", "on"))
    assert dim_on["success-rate"] == 0.75 and dim_on["episodes"] == 8 and dim_on["vs-span"] == 0.75
    assert dim_on["per-seed"] == [0.75, 0.75]
    assert dim_on["mcnemar-p-on-vs-off"] == pytest.approx(2 * 0.5**6)  # 6 discordant episodes, all one way
    met = targets(rows)
    assert met == {"global >= 0.8x in lighting": False, "personal >= 0.8x in own lighting": False,
                   "global in span within noise": True}  # fmt: skip


@pytest.mark.allowance(360)
@pytest.mark.e2e
def test_the_robustness_benchmark_trains_rolls_out_and_continues_from_its_folder(tmp_path, capsys):
    """One owner, one round: the global model through ``flwr run``, the centralised and personal
    models in process, each with and without transforms, rolled out in the server's span, outside
    it and in the owner's own set-up made dim. Run again, the same command takes every model and
    rollout from its folder and prints the same table."""
    from zk0.bench.robustness import main

    argv = ["--seeds", "7", "--clients", "1", "--demos", "4", "--rounds", "1", "--local-steps", "1"]
    argv += ["--personal-steps", "1", "--batch-size", "2", "--model", "tiny", "--sim-episodes", "2"]
    argv += ["--episode-length", "40"]
    argv += ["--conditions", "dim-0", "--owner-conditions", "dim-0", "--output-dir", str(tmp_path)]
    argv += ["--json", str(tmp_path / "robustness.json")]
    assert main(argv) == 0
    first = capsys.readouterr().out
    figures = json.loads((tmp_path / "robustness.json").read_text())
    kept = [json.loads(p.read_text()) for p in tmp_path.rglob("rollouts-2x40/*/*.json")]
    assert kept and all(r["episode-length"] <= 40 for r in kept), "episodes end at --episode-length"
    rolled = figures["seeds"]["7"]
    assert list(rolled) == ["off", "on"]
    for label in ("off", "on"):
        assert {m: list(c) for m, c in rolled[label].items()} == {
            "global": ["server", "dim-0"],
            "centralised": ["server", "dim-0"],
            "personal 0": ["client 0", "client 0 dim-0"],
        }
        assert all(len(r["outcomes"]) == 2 for columns in rolled[label].values() for r in columns.values())
    models = tmp_path / "seed-7"
    assert (models / "transforms-off" / "models" / "global.safetensors").read_bytes() != (
        models / "transforms-on" / "models" / "global.safetensors"
    ).read_bytes(), "the federation with transforms trained on other frames"
    assert len(figures["rows"]) == 2 * 6 and set(figures["targets"]) == {
        "global >= 0.8x in lighting", "personal >= 0.8x in own lighting", "global in span within noise",
    }  # fmt: skip
    assert "sim-cube owners: 1 x 4 demonstrations" in first and "personal 0   client 0 dim-0" in first

    assert main(argv) == 0
    again = capsys.readouterr().out
    assert "(kept from an earlier run)" in again
    assert again.split("sim-cube owners: ")[-1] == first.split("sim-cube owners: ")[-1]
