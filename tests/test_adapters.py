"""LoRA on the wire (zk0.learning.adapters): lerobot's PEFT wrapping, identical on every party; only the
adapters train and travel; checkpoints are plain lerobot directories with the adapters merged."""

from __future__ import annotations

import json

import pytest
import torch
from flwr.app import ArrayRecord
from lerobot.configs import PreTrainedConfig
from lerobot.policies import make_policy
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from safetensors.torch import load_file

from zk0.artifacts.resume import find_resume_point
from zk0.artifacts.run_folder import save_checkpoint
from zk0.common.errors import Zk0Error
from zk0.config import LORA_FULL_MODULES, ConfigError, RunConfig, from_run_config
from zk0.data.loaders import open_metadata, prepare_batch
from zk0.deployment.simulation import cpu_federation, flwr_run
from zk0.federation.client import build_client
from zk0.federation.wire import encode
from zk0.learning.policy import backbone_fingerprint, build_policy, set_trainable, trainable_tensors


@pytest.fixture(scope="module")
def start(tmp_path_factory, registry):
    """A pretrained starting point: the tiny policy saved as a zk0 checkpoint (lerobot adapts only
    pretrained weights)."""
    entry = registry.clients[0]
    bundle = build_policy(RunConfig(device="cpu"), open_metadata(entry), entry, registry.model_cameras())
    return save_checkpoint(bundle, tmp_path_factory.mktemp("start"), 0, {})


def merged_key(name: str) -> str:
    """The plain policy's tensor a trained one lands in when merged: an adapted layer's weight, or
    the projection trained in full itself."""
    name = name.removeprefix("base_model.model.")
    return name.split(".lora_")[0] + ".weight" if ".lora_" in name else name.replace(".modules_to_save.default", "")


def lora_run(start, **keys) -> RunConfig:
    return from_run_config({"model": str(start), "peft": "lora", "batch-size": 4, "local-steps": 3, **keys})


@pytest.mark.parametrize(
    ("keys", "sentence"),
    [
        ({"peft": "qlora"}, "Run-config key 'peft' got 'qlora'; expected one of ['none', 'lora']."),
        ({"lora-average": "a"}, "Run-config key 'lora-average' got 'a'; expected one of ['b', 'ab']."),
        ({"lora-rank": 0}, "Run-config key 'lora-rank' got 0; expected a value >= 1."),
        ({"lora-alpha": 0}, "Run-config key 'lora-alpha' got 0.0; expected a value > 0."),
        ({"lora-targets": "q_proj("}, "Run-config key 'lora-targets' got 'q_proj(', which is not a regular expression"),
        ({"peft": "lora"}, "Run-config key 'peft' = 'lora' adapts a pretrained SmolVLA, and model='tiny' has random"),
    ],
)
def test_lora_keys_are_refused_in_one_sentence(keys, sentence):
    with pytest.raises(ConfigError) as err:
        from_run_config(keys)
    assert str(err.value).startswith(sentence)
    assert str(err.value).endswith(".") and "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("keys", "sentence"),
    [
        ({"lora-targets": r"no_such_module"}, "lerobot cannot add LoRA adapters with these lora-* keys: "),
        (
            {"lora-full-modules": "state_proj,state_prj"},
            "Run-config key 'lora-full-modules' names 'state_prj', which matches no module of this SmolVLA; ",
        ),
    ],
)
def test_lora_keys_that_match_no_module_are_refused(start, registry, keys, sentence):
    entry = registry.clients[0]
    with pytest.raises(Zk0Error) as err:
        build_policy(lora_run(start, **keys), open_metadata(entry), entry, registry.model_cameras())
    assert str(err.value).startswith(sentence) and "\n" not in str(err.value)


@pytest.mark.parametrize(("average", "travels"), [("b", {"lora_B"}), ("ab", {"lora_A", "lora_B"})])
def test_every_party_wraps_identically_and_only_adapters_train(start, registry, average, travels):
    """Two clients on different datasets: same frozen base and adapter start (one fingerprint), and a
    round of local steps changes the travelling adapter tensors and nothing else."""
    run = lora_run(start, **{"lora-average": average, "lora-full-modules": ""})  # every target adapted
    clients = [build_client(run, entry, registry.model_cameras(), i) for i, entry in enumerate(registry.clients[:2])]
    a, b = (c.bundle for c in clients)
    assert a.trainable_names == b.trainable_names
    assert {name.split(".")[-3] for name in a.trainable_names} == travels  # ...q_proj.lora_B.default.weight
    assert backbone_fingerprint(a) == backbone_fingerprint(b)
    assert (
        clients[0].fingerprint
        != build_client(
            RunConfig(model=str(start), batch_size=4), registry.clients[0], registry.model_cameras()
        ).fingerprint
    ), "the fingerprint covers the adapters' frozen start, not only the base"
    first, second = trainable_tensors(a), trainable_tensors(b)
    assert all(torch.equal(first[n], second[n]) for n in first), "the adapters start bit-identical"
    assert all(not t.any() for n, t in first.items() if ".lora_B." in n), "LoRA starts at B = 0"

    trainer = clients[0].trainer
    assert set(trainer.fedprox.params) == set(a.trainable_names), "FedProx anchors the adapters"
    before = {n: p.detach().clone() for n, p in a.policy.named_parameters()}
    trainer.fit(3, mu=0.01, global_step=0)
    after = dict(a.policy.named_parameters())
    changed = {n for n in before if not torch.equal(before[n], after[n].detach())}
    assert changed and changed <= set(a.trainable_names), sorted(changed - set(a.trainable_names))[:3]
    assert {n for n in changed if ".lora_B." in n}, "B learned something"


def test_checkpoint_is_a_plain_lerobot_policy_with_the_adapters_merged(start, registry, tmp_path):
    """What lerobot's factory loads from the checkpoint predicts what the adapted policy predicts,
    and a resumed run gets the very adapter tensors back."""
    entry = registry.clients[0]
    run = lora_run(start)
    client = build_client(run, entry, registry.model_cameras())
    bundle = client.bundle
    trained = {n: torch.randn_like(t) * 0.05 for n, t in trainable_tensors(bundle).items()}
    set_trainable(bundle, trained)
    (tmp_path / "server").mkdir()
    checkpoint = save_checkpoint(bundle, tmp_path, 2, {})

    cfg = PreTrainedConfig.from_pretrained(checkpoint)
    cfg.pretrained_path = checkpoint
    assert cfg.use_peft is False
    meta = open_metadata(entry)
    loaded = make_policy(cfg, ds_meta=meta, rename_map=entry.rename_map())
    assert type(loaded) is SmolVLAPolicy
    assert not any("lora" in name for name in loaded.state_dict())

    batch = next(iter(client.eval_batches))
    batch = bundle.preprocessor(prepare_batch(batch, meta.camera_keys, entry.task, bundle.device))
    chunks = []
    for policy in (bundle.policy, loaded):
        policy.eval()
        torch.manual_seed(7)
        chunks.append(policy.predict_action_chunk(batch))
    torch.testing.assert_close(chunks[1], chunks[0], atol=1e-4, rtol=1e-4)
    base = load_file(start / "model.safetensors")
    merged = load_file(checkpoint / "model.safetensors")
    changed = {k for k in base if not torch.equal(base[k], merged[k])}
    assert changed == {merged_key(n) for n in trained}, "exactly the adapted layers' and projections' weights changed"

    adapter = json.loads((checkpoint / "adapter" / "adapter_config.json").read_text())
    assert adapter["r"] == run.lora_rank and adapter["peft_type"] == "LORA"
    fresh = build_client(run, registry.clients[1], registry.model_cameras(), 1).bundle
    resumed = find_resume_point(str(tmp_path)).trainable(fresh).to_torch_state_dict()
    assert set(resumed) == set(trained)
    assert all(torch.equal(resumed[n], trained[n]) for n in trained)


@pytest.mark.e2e
def test_lora_federation_sends_only_adapters_and_checkpoints_a_loadable_policy(start, registry, flower_env, tmp_path):
    """2 clients x 2 rounds of `flwr run` with peft = "lora" from a pretrained start."""
    out = tmp_path / "outputs"
    log = flwr_run(
        flower_env,
        f"num-server-rounds=2 local-steps=3 batch-size=4 peft='lora' model='{start}' output-dir='{out}'",
        cpu_federation(num_supernodes=2, actors=1),
    )
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1 and "Done in " in log, log[-3000:]
    history = json.loads((runs[0] / "server" / "metrics_history.json").read_text())

    entry = registry.clients[0]
    adapted = build_policy(lora_run(start), open_metadata(entry), entry, registry.model_cameras())
    adapters = trainable_tensors(adapted)
    assert all(".lora_B." in name or ".modules_to_save." in name for name in adapters)
    for record in history["rounds"]:
        assert record["global-arrays"] == {"tensors": len(adapters), "bytes": ArrayRecord(adapters).count_bytes()}
    for client in history["rounds"][-1]["clients"].values():
        assert client["train"]["update-bytes"] == encode(adapters, "bfloat16").count_bytes(), "the adapters alone"
    assert history["rounds"][-1]["server-evaluate"]["action-mse"] > 0

    checkpoint = runs[0] / "models" / "checkpoint_round_2"
    cfg = PreTrainedConfig.from_pretrained(checkpoint)
    cfg.pretrained_path = checkpoint
    policy = make_policy(cfg, ds_meta=open_metadata(entry), rename_map=entry.rename_map())
    assert type(policy) is SmolVLAPolicy
    base, merged = load_file(start / "model.safetensors"), load_file(checkpoint / "model.safetensors")
    assert any(not torch.equal(base[k], merged[k]) for k in base), "two rounds of adapters are merged in"
    client = build_client(RunConfig(model=str(checkpoint), batch_size=4), entry, registry.model_cameras())
    batch = next(iter(client.eval_batches))
    batch = client.bundle.preprocessor(
        prepare_batch(batch, client.split.meta.camera_keys, entry.task, client.bundle.device)
    )
    policy.eval()
    chunk = policy.predict_action_chunk(batch)
    assert chunk.shape == (4, policy.config.chunk_size, 6) and torch.isfinite(chunk).all()


@pytest.mark.e2e
def test_a_federation_with_targets_that_match_nothing_says_so_in_one_sentence(start, flower_env, tmp_path):
    """The ServerApp builds the global model before round 1: lerobot's refusal reaches the log as one sentence."""
    log = flwr_run(
        flower_env,
        f"peft='lora' lora-targets='no_such_module' model='{start}' output-dir='{tmp_path / 'outputs'}'",
        cpu_federation(num_supernodes=2, actors=1),
    )
    assert "zk0: lerobot cannot add LoRA adapters with these lora-* keys: " in log, log[-3000:]
    assert "Done in " not in log


def test_small_projections_train_in_full_next_to_the_adapters(start, registry, tmp_path):
    """The default lora-full-modules: SmolVLA's five small projections travel whole next to the
    expert's adapters (not adapted themselves), and the merged checkpoint carries them as trained."""
    entry = registry.clients[0]
    bundle = build_client(lora_run(start), entry, registry.model_cameras()).bundle
    whole = [n for n in bundle.trainable_names if ".lora_" not in n]
    assert {n.split(".")[-4] for n in whole} == set(LORA_FULL_MODULES.split(","))  # ...state_proj.modules_to_save...
    assert all(".lm_expert." in n for n in bundle.trainable_names if ".lora_" in n), "adapters on the expert only"
    trained = {n: t + 0.05 for n, t in trainable_tensors(bundle).items()}
    set_trainable(bundle, trained)
    (tmp_path / "server").mkdir()
    checkpoint = save_checkpoint(bundle, tmp_path, 1, {})
    merged = load_file(checkpoint / "model.safetensors")
    for name in whole:
        assert torch.equal(merged[merged_key(name)], trained[name]), name
