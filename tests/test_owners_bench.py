"""python -m zk0.bench owners: the same training with more owners, judged where no owner was."""

from __future__ import annotations

import json

import pytest

from zk0.bench.owners import build_parser, check, table


def test_the_table_pools_seeds_and_compares_every_size_with_the_smallest_on_the_same_episodes():
    def rates(outcomes):
        return {"outcomes": outcomes, "success-rate": sum(outcomes) / len(outcomes)}

    def rolled(server, unseen):
        return {"global": {"server": rates(server), "u0": rates(unseen), "u1": rates(unseen)},
                "personal 0": {"client 0": rates(server)}}  # fmt: skip

    results = {4: {1: rolled([0, 0, 0, 0], [0, 0]), 2: rolled([0, 0, 0, 0], [0, 1])},
               64: {1: rolled([1, 1, 1, 0], [1, 1]), 2: rolled([1, 1, 1, 1], [1, 1])}}  # fmt: skip
    rows = {(r["owners"], r["model"]): r for r in table(results, ["u0", "u1"], personal_owners=1)}
    big = rows[64, "global, server's span"]
    assert big["success-rate"] == 7 / 8 and big["episodes"] == 8
    assert big["mcnemar-p-vs-smallest"] == pytest.approx(2 * 0.5**7)  # 7 discordant episodes, all one way
    unseen = rows[4, "global, unseen owners"]
    assert (unseen["episodes"], unseen["success-rate"]) == (8, 2 / 8)
    assert rows[4, "global, server's span"]["mcnemar-p-vs-smallest"] == 1.0
    assert rows[64, "personal, own set-ups"]["episodes"] == 8, "every personal model's episodes, every seed"
    assert set(rows) == {(n, m) for n in (4, 64) for m in ("global, server's span", "global, unseen owners",
                                                          "personal, own set-ups", "personal 0, own set-up")}  # fmt: skip


def test_sizes_that_cannot_compare_are_refused_in_one_sentence(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit):
        check(parser, parser.parse_args(["--sizes", "2", "16"]))
    assert "--sizes got [2, 16]; expected different sizes, each at least --per-round (4) and --personal-owners (4" in (
        capsys.readouterr().err
    )


@pytest.mark.allowance(360)
@pytest.mark.e2e
def test_the_owners_benchmark_trains_each_size_and_judges_it_where_no_owner_was(tmp_path, capsys):
    """One owner and two, one sampled a round: each federation through ``flwr run``, its global model
    rolled out in the server's span and in the set-up of an owner in neither run, owner 0's personal
    model in its own; run again, everything comes from the folder."""
    from zk0.bench.owners import main

    argv = ["--sizes", "1", "2", "--per-round", "1", "--personal-owners", "1", "--demos", "4", "--rounds", "1"]
    argv += ["--local-steps", "1", "--personal-steps", "1", "--seeds", "7", "--unseen", "1", "--sim-episodes", "2"]
    argv += ["--episode-length", "40"]
    argv += ["--model", "tiny", "--batch-size", "2", "--output-dir", str(tmp_path), "--json", str(tmp_path / "o.json")]
    assert main(argv) == 0
    first = capsys.readouterr().out
    figures = json.loads((tmp_path / "o.json").read_text())
    kept = [json.loads(p.read_text()) for p in tmp_path.rglob("rollouts-2x40/*/*.json")]
    assert kept and all(r["episode-length"] <= 40 for r in kept), "episodes end at --episode-length"
    assert figures["unseen"] == ["sim-so101-owner-2-cube"]
    for size in ("1", "2"):
        rolled = figures["rollouts"][size]["7"]
        assert {m: list(c) for m, c in rolled.items()} == {
            "global": ["server", "sim-so101-owner-2-cube"],
            "personal 0": ["client 0"],
        }
        history = json.loads(next((tmp_path / f"owners-{size}").rglob("metrics_history.json")).read_text())
        trained = [[i for i, c in r["clients"].items() if "train" in c] for r in history["rounds"] if r["round"]]
        assert [len(t) for t in trained] == [1], "one owner sampled a round, whatever the size"
    assert len(figures["rows"]) == 2 * 4
    assert (tmp_path / "owners.png").stat().st_size > 10_000, "the curve"
    assert main(argv) == 0
    again = capsys.readouterr().out
    assert "(kept from an earlier run)" in again
    assert again.split("episodes per seed")[-1] == first.split("episodes per seed")[-1]
