"""The public starting point: public set-ups apart from every owner's and every evaluation
condition, the registry's public role, and `zk0 pretrain` writing a policy a federation starts from."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from zk0.common.catalogue import MAX_OWNERS
from zk0.data.registry import RegistryError, load_registry


def test_no_public_setup_is_an_owners_or_an_evaluation_condition():
    """64 public set-ups against every generated owner (0-999), the hand-written owners and the
    server's set, and the conditions outside the span the benchmarks judge in: no room (look), no
    cube region and no name in common, so no public demonstration is recorded where an owner's or
    an evaluation episode is."""
    from zk0.sim.tasks import OUTSIDE, OWNERS, outside_condition, sim_owner, sim_public

    public = [sim_public(i) for i in range(64)]
    bases = [None, *(o for o in OWNERS if o.role == "client")]
    others = [*OWNERS, *map(sim_owner, range(MAX_OWNERS))]
    others += [outside_condition(axis, i, base) for axis in OUTSIDE for i in range(8) for base in bases]
    assert not {s.task.look for s in public} & {s.task.look for s in others}
    assert not {s.task.region for s in public} & {s.task.region for s in others}
    assert not {s.name for s in public} & {s.name for s in others}
    assert not {s.repo_id for s in public} & {s.repo_id for s in others}


def test_the_owners_table_adds_public_sets_and_a_public_set_is_no_one_elses(tmp_path):
    path = tmp_path / "registry.toml"
    path.write_text('[tool.zk0.owners]\ncount = 2\nkind = "sim-cube"\npublic = 3\n')
    registry = load_registry(path)
    assert [e.name for e in registry.clients] == ["sim-so101-owner-0-cube", "sim-so101-owner-1-cube"]
    assert [e.name for e in registry.public] == [f"sim-so101-public-{i}-cube" for i in range(3)]
    assert registry.server.name == "sim-so101-eval-cube"
    bad = {
        "count = 2\npublic = 1\n": "[tool.zk0.owners] public = 1 needs a simulated kind; expected kind one of",
        'count = 2\nkind = "sim"\npublic = "many"\n': "[tool.zk0.owners] public = 'many'; expected a whole number",
    }
    for table, sentence in bad.items():
        path.write_text(f"[tool.zk0.owners]\n{table}")
        with pytest.raises(RegistryError, match=r"^" + sentence.replace("[", r"\[").replace("]", r"\]")):
            load_registry(path)
    path.write_text(
        '[tool.zk0.datasets.mine]\nrepo_id = "me/mine"\ncameras = { top = "camera1" }\n'
        '[tool.zk0.datasets.open]\nrepo_id = "me/mine"\nrole = "public"\ncameras = { top = "camera1" }\n'
    )
    with pytest.raises(
        RegistryError, match="Registry entries 'open' \\(public\\) and 'mine' \\(client\\) are the same"
    ):
        load_registry(path)


@pytest.mark.slow
def test_zk0_pretrain_writes_a_policy_that_lerobot_loads_and_a_federation_starts_from(tmp_path, capsys):
    """Two public sets, three steps of the tiny SmolVLA: a lerobot policy folder whose processors
    normalise by both sets' merged statistics, each set's own kept beside them; an owner's client
    built with model='<folder>' starts from its weights; the command says how to federate from it,
    and refuses a folder that exists and a registry with no public sets in one sentence each."""
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from safetensors.torch import load_file

    from zk0.cli import main
    from zk0.config import from_run_config
    from zk0.data.assets import ensure_dataset
    from zk0.federation.client import build_client
    from zk0.learning.policy import snapshot

    registry_path = tmp_path / "registry.toml"
    registry_path.write_text('[tool.zk0.owners]\ncount = 1\nkind = "sim-cube"\npublic = 2\n')
    registry = load_registry(registry_path)
    for entry in registry.entries:
        ensure_dataset(entry.name)
    out = tmp_path / "public-base"
    config = f"registry='{registry_path}' model='tiny' batch-size=2"
    assert main(["pretrain", "--run-config", config, "--steps", "3", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "Pretrained smolvla (tiny) for 3 steps on 2 public set(s)" in said
    assert f"flwr run . --run-config \"registry='{registry_path}' model='{out}'\"" in said

    policy = SmolVLAPolicy.from_pretrained(out)
    assert type(policy).__name__ == "SmolVLAPolicy"
    kept = {p.stem: json.loads(p.read_text()) for p in (out / "client_stats").glob("*.json")}
    assert set(kept) == {"sim-so101-public-0-cube", "sim-so101-public-1-cube"}
    merged = aggregate_stats(
        [{f: {k: np.asarray(v) for k, v in s.items()} for f, s in st.items()} for st in kept.values()]
    )
    normaliser = load_file(next(out.glob("policy_preprocessor_step_*_normalizer_processor.safetensors")))
    mean = normaliser["observation.state.mean"].numpy()
    assert mean.tolist() == pytest.approx(merged["observation.state"]["mean"].tolist(), rel=1e-5)

    run = from_run_config({"registry": str(registry_path), "model": str(out), "batch-size": 2})
    owner = build_client(run, registry.clients[0], registry.model_cameras())
    saved = load_file(out / "model.safetensors")
    assert all(torch.equal(weight, saved[name]) for name, weight in snapshot(owner.bundle).items())

    assert main(["pretrain", "--run-config", config, "--steps", "3", "--out", str(out)]) == 2
    assert f"zk0: --out {str(out)!r} exists; expected a new folder" in capsys.readouterr().err
    assert main(["pretrain", "--run-config", "model='tiny'", "--out", str(tmp_path / "other")]) == 2
    assert "has no public datasets to pretrain on" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_monna_without_public_sets_is_refused_before_round_1():
    from zk0.config import ConfigError, from_run_config
    from zk0.server_app import trusted_direction

    run = from_run_config({"aggregation": "monna", "min-train-clients": 3})
    with pytest.raises(
        ConfigError, match="'aggregation' = 'monna' scores the owners' updates against the server's own"
    ):
        trusted_direction(run, load_registry())
    assert trusted_direction(from_run_config({}), load_registry()) is None, "no other rule trains on the server"


@pytest.mark.slow
def test_the_servers_trusted_update_is_trained_on_the_public_sets_the_same_in_a_rerun(tmp_path):
    """The server's update on two public sets from a round's global model: it moves the model, a
    second server (as after a resume) computes the same vector for the same round, and the next
    round's differs (its batches come after this round's)."""
    from zk0.config import from_run_config
    from zk0.data.assets import ensure_dataset
    from zk0.federation.trusted import TrustedDirection
    from zk0.learning.policy import trainable_tensors

    registry_path = tmp_path / "registry.toml"
    registry_path.write_text('[tool.zk0.owners]\ncount = 1\nkind = "sim-cube"\npublic = 2\n')
    registry = load_registry(registry_path)
    for entry in registry.entries:
        ensure_dataset(entry.name)
    run = from_run_config({"registry": str(registry_path), "model": "tiny", "batch-size": 2, "local-steps": 2})
    server = TrustedDirection(run, registry)
    current = {name: t.numpy().copy() for name, t in trainable_tensors(server.bundle).items()}
    first = server.update(1, current)
    assert first.numel() == sum(a.size for a in current.values()) and float(first.norm()) > 0
    assert not torch.equal(server.update(2, current), first), "round 2 trains on the batches after round 1's"
    assert torch.equal(TrustedDirection(run, registry).update(1, current), first), "a rerun's round 1 is the same"
