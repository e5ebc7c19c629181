"""``zk0 export``: an owner's policy out of a run, loaded back with lerobot's own loaders."""

import numpy as np
import pytest
import torch
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from lerobot.processor import PolicyProcessorPipeline

from zk0.artifacts.run_folder import PERSONAL, client_dir, save_checkpoint
from zk0.cli import main
from zk0.config import RunConfig
from zk0.data.loaders import open_metadata
from zk0.learning.policy import build_policy


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, registry):
    """A run folder as a federation leaves it: two checkpoints whose processors carry the merged
    statistics, each owner's own in ``client_stats/``, and client 1's personal model."""
    entry = registry.clients[0]
    bundle = build_policy(RunConfig(device="cpu"), open_metadata(entry), entry, registry.model_cameras())
    run = tmp_path_factory.mktemp("run")
    (run / "server").mkdir()
    owners = {f"client_{i}_{entry.name}": owner_stats(bundle.stats, 1.0 + i) for i in range(2)}
    for rnd in (1, 2):
        save_checkpoint(bundle, run, rnd, owners)
    save_checkpoint(bundle, client_dir(run, 1), 2, {}, PERSONAL)
    return run


def owner_stats(stats: dict, scale: float) -> dict:
    """An owner's statistics: the merged ones with the action's mean moved by ``scale``."""
    mine = {feature: dict(values) for feature, values in stats.items()}
    mine["action"]["mean"] = np.asarray(stats["action"]["mean"]) + scale
    return mine


def normaliser_stats(folder, config: str) -> dict:
    """The statistics of a saved pipeline's (un)normaliser, as lerobot loads them."""
    pipeline = PolicyProcessorPipeline.from_pretrained(folder, f"{config}.json")
    (step,) = [s for s in pipeline.steps if hasattr(s, "stats") and s.stats]
    return step.stats


def test_the_global_model_is_exported_with_the_owners_statistics_and_lerobot_loads_it(run_dir, tmp_path, capsys):
    out = tmp_path / "mine"
    assert main(["export", str(run_dir), "--client", "1", "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    merged = normaliser_stats(run_dir / "models" / "checkpoint_round_2", "policy_preprocessor")["action"]["mean"]
    for config in ("policy_preprocessor", "policy_postprocessor"):
        mean = normaliser_stats(out, config)["action"]["mean"]
        np.testing.assert_allclose(np.asarray(mean), np.asarray(merged) + 2.0, rtol=1e-6)
    assert not (out / "client_stats").exists() and not (out / "server_optimiser.safetensors").exists()
    policy = SmolVLAPolicy.from_pretrained(out)
    kept = SmolVLAPolicy.from_pretrained(run_dir / "models" / "checkpoint_round_2")
    for (name, a), (_, b) in zip(policy.state_dict().items(), kept.state_dict().items(), strict=True):
        assert torch.equal(a, b), name


def test_the_personal_model_is_exported_as_its_client_kept_it(run_dir, tmp_path):
    out = tmp_path / "personal"
    assert main(["export", str(run_dir), "--client", "1", "--personal", "--out", str(out)]) == 0
    kept = client_dir(run_dir, 1) / "models" / PERSONAL
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in kept.iterdir())
    assert (out / "model.safetensors").read_bytes() == (kept / "model.safetensors").read_bytes()


@pytest.mark.parametrize(
    ("argv", "sentence"),
    [
        (["--client", "5"], "--client got 5; this checkpoint keeps the statistics of clients [0, 1]."),
        (["--client", "0", "--round", "7"], "--round got 7; this run has checkpoints of rounds [1, 2]."),
        (["--client", "0", "--personal"], "Client 0 has no personal model in"),
        (["--client", "1", "--personal", "--round", "1"], "--round names a global checkpoint;"),
    ],
)
def test_a_bad_export_is_one_sentence_and_writes_nothing(run_dir, tmp_path, capsys, argv, sentence):
    out = tmp_path / "never"
    assert main(["export", str(run_dir), *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("zk0: ") and sentence in err and err.count("\n") == 1
    assert not out.exists() and not list(tmp_path.glob(".never*"))


def test_an_export_never_writes_over_a_folder_with_files(run_dir, tmp_path, capsys):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["export", str(run_dir), "--client", "0", "--out", str(out)]) == 2
    assert "already holds files" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
