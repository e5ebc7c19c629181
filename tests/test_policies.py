"""ACT and Diffusion Policy beside SmolVLA: the ``policy`` key, built by lerobot's factories offline,
refused in one sentence where a combination cannot work, and federated through `flwr run` into
checkpoints that lerobot's own loader and `lerobot-eval` take."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from zk0.config import ConfigError, from_run_config
from zk0.data.assets import ensure_dataset
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry
from zk0.learning.policy import PolicyError, build_policy, get_trainable

SIM_REGISTRY = "configs/sim-registry.toml"
SIM_CAMERAS = {"observation.images.front": "observation.images.camera1", "observation.images.wrist": "observation.images.camera2"}


@pytest.mark.parametrize(
    ("config", "said"),
    [
        ({"policy": "pi0"}, "Run-config key 'policy' got 'pi0'; expected one of ['smolvla', 'act', 'diffusion']."),
        (
            {"policy": "diffusion", "compile": True},
            "Run-config key 'compile' = true compiles SmolVLA's training forward (lerobot's compile_model), and "
            "zk0 compiles no other policy (policy='diffusion'); expected compile=false.",
        ),
        (
            {"policy": "act", "peft": "lora", "model": "some/checkpoint"},
            "Run-config key 'peft' = 'lora' adapts SmolVLA, and policy='act' trains in full; expected peft='none'.",
        ),
    ],
)
def test_a_policy_zk0_cannot_build_is_refused_in_one_sentence(config, said):
    with pytest.raises(ConfigError) as refused:
        from_run_config(config)
    assert str(refused.value) == said


def act_bundle(registry, **run):
    entry = registry.clients[0]
    return build_policy(from_run_config({"policy": "act", **run}), open_metadata(entry), entry, registry.model_cameras())


def test_act_is_built_from_random_weights_trains_everything_and_is_the_same_on_every_party(registry):
    """No ImageNet download: the ResNet starts from the run's seed, so two parties' starting models
    are equal, and every parameter (the ResNet's too) is trainable and travels."""
    first, second = act_bundle(registry), act_bundle(registry)
    assert type(first.policy).__name__ == "ACTPolicy" and first.policy.config.pretrained_backbone_weights is None
    assert first.trainable_names == [name for name, _ in first.policy.named_parameters()]
    assert any(name.startswith("model.backbone.") for name in first.trainable_names)
    a, b = get_trainable(first).to_torch_state_dict(), get_trainable(second).to_torch_state_dict()
    assert all(torch.equal(a[name], b[name]) for name in a)
    assert first.policy.config.dim_model == 128, "tiny: a CPU size"
    assert act_bundle(registry, model="full-size").policy.config.dim_model == 512, "lerobot's default"


def test_a_checkpoint_of_another_type_or_one_naming_imagenet_weights(registry, tmp_path):
    """An ACT checkpoint with the default policy is refused in one sentence naming the key to set;
    one whose config names torchvision's ImageNet weights (as lerobot's own ACT checkpoints do)
    builds offline, its weights the checkpoint's."""
    bundle = act_bundle(registry)
    checkpoint = tmp_path / "act"
    for part in (bundle.policy, bundle.preprocessor, bundle.postprocessor):
        part.save_pretrained(checkpoint)
    with pytest.raises(PolicyError) as refused:
        build_policy(from_run_config({"model": str(checkpoint)}), None, registry.clients[0], [])
    assert str(refused.value) == (
        f"Model '{checkpoint}' is a lerobot policy of type 'act' and the run says policy='smolvla'; "
        "set policy='act' to fine-tune it."
    )
    config = json.loads((checkpoint / "config.json").read_text())
    config["pretrained_backbone_weights"] = "ResNet18_Weights.IMAGENET1K_V1"
    (checkpoint / "config.json").write_text(json.dumps(config))
    loaded = act_bundle(registry, model=str(checkpoint))
    saved, start = get_trainable(loaded).to_torch_state_dict(), get_trainable(bundle).to_torch_state_dict()
    assert all(torch.equal(saved[name], start[name]) for name in start)


def test_act_refuses_a_dataset_without_every_model_camera_in_one_sentence(registry):
    """SmolVLA fills a camera a dataset lacks with an empty slot; ACT has none, so it says what to map."""
    entry = registry.clients[0]
    one = replace(entry, cameras=dict(list(entry.cameras.items())[:1]))
    run = from_run_config({"policy": "act"})
    with pytest.raises(PolicyError) as refused:
        build_policy(run, open_metadata(one), one, registry.model_cameras())
    said = str(refused.value)
    assert said.startswith(f"Dataset {entry.name!r} records nothing for the model's camera input(s) ")
    assert "ACT has no empty-camera slots" in said and "\n" not in said


def diffusion_bundle(registry, meta=None, **run):
    entry = registry.clients[0]
    run = from_run_config({"policy": "diffusion", **run})
    return build_policy(run, meta or open_metadata(entry), entry, registry.model_cameras())


def test_diffusion_is_built_from_random_weights_with_group_norm_and_a_horizon_that_holds_the_chunk(registry):
    """As the paper trains it without ImageNet weights: GroupNorm for BatchNorm, every parameter
    trained and equal on every party; the two latest observations, ``chunk-size`` actions played
    from the latest, in a horizon the U-Net's three halvings divide; few DDIM steps when tiny."""
    first, second = diffusion_bundle(registry), diffusion_bundle(registry)
    cfg = first.policy.config
    assert type(first.policy).__name__ == "DiffusionPolicy" and cfg.pretrained_backbone_weights is None
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in first.policy.modules())
    assert first.trainable_names == [name for name, _ in first.policy.named_parameters()]
    a, b = get_trainable(first).to_torch_state_dict(), get_trainable(second).to_torch_state_dict()
    assert all(torch.equal(a[name], b[name]) for name in a)
    assert (cfg.n_obs_steps, cfg.n_action_steps, cfg.horizon) == (2, 10, 16)
    assert cfg.action_delta_indices[cfg.n_obs_steps - 1] == 0, "the chunk starts at the latest observation"
    assert (cfg.noise_scheduler_type, cfg.num_inference_steps, cfg.down_dims) == ("DDIM", 10, (64, 128, 256))
    assert cfg.scheduler_warmup_steps == 0, "a tenth of the run's 2 steps: lerobot's 500 would be all of them"
    longer = diffusion_bundle(registry, **{"chunk-size": 20, "num-server-rounds": 100, "local-steps": 100})
    assert (longer.policy.config.horizon, longer.policy.config.scheduler_warmup_steps) == (24, 500)
    full = diffusion_bundle(registry, model="full-size").policy.config
    assert (full.down_dims, full.noise_scheduler_type) == ((512, 1024, 2048), "DDPM"), "lerobot's default"


def test_diffusions_action_window_starts_an_observation_back_and_is_judged_from_the_latest(registry):
    """lerobot hands Diffusion Policy the actions from its oldest observation on; its chunk starts
    at the latest, so the held-out MSE compares it with the window from there: that entry is the
    action a policy whose window starts now (ACT's) gets first."""
    from zk0.data.loaders import open_split
    from zk0.learning.training import chunk_start

    entry = registry.clients[0]
    meta = open_metadata(entry)
    windows = {}
    for policy in ("act", "diffusion"):
        run = from_run_config({"policy": policy})
        cfg = build_policy(run, meta, entry, registry.model_cameras()).policy.config
        sample = open_split(entry, meta, cfg, run).evaluation[5]
        windows[policy] = sample["action"][chunk_start(cfg) :]
    assert torch.equal(windows["diffusion"][:10], windows["act"][:10])
    assert not torch.equal(windows["diffusion"][:10], windows["act"][1:11]), "the actions move"


def test_diffusion_refuses_cameras_of_two_sizes_in_lerobots_words(registry):
    """lerobot's Diffusion Policy stacks its cameras, so they must be one size: a dataset whose
    cameras differ is refused in one sentence naming it, before anything trains."""
    entry = registry.clients[0]
    meta = open_metadata(entry)
    wrist = meta.info.features[meta.camera_keys[1]]
    wrist["shape"] = (96, 128, 3)
    with pytest.raises(PolicyError) as refused:
        diffusion_bundle(registry, meta)
    said = str(refused.value)
    assert said.startswith(f"Dataset {entry.name!r} cannot feed Diffusion Policy as lerobot builds it: ")
    assert "we expect all image shapes to match" in said and "\n" not in said


def test_a_dataset_without_a_statistic_the_policy_normalises_by_is_refused_in_one_sentence(registry):
    """lerobot's normaliser would stop at the first batch (or pass a feature with no statistics
    through unscaled): a dataset lacking what the policy reads is refused before anything trains.
    Diffusion Policy scales actions by their min and max; ACT by mean and std, so it builds."""
    entry = registry.clients[0]
    meta = open_metadata(entry)
    del meta.stats["action"]["min"]
    with pytest.raises(PolicyError) as refused:
        diffusion_bundle(registry, meta)
    assert str(refused.value) == (
        f"Dataset {entry.name!r} has no min statistics for 'action', which Diffusion Policy normalises by MIN_MAX; "
        "expected them in its meta/stats.json, as lerobot records them."
    )
    assert build_policy(from_run_config({"policy": "act"}), meta, entry, registry.model_cameras()).policy
    camera = next(iter(entry.cameras))
    del meta.stats[f"observation.images.{camera}"]
    with pytest.raises(PolicyError, match=r"has no mean or std statistics for 'observation.images.camera1', which ACT"):
        build_policy(from_run_config({"policy": "act"}), meta, entry, registry.model_cameras())


def test_the_policies_benchmark_builds_each_type_offline_or_says_why_not(tmp_path, capsys):
    """A row per lerobot policy type: ACT builds as zk0 federates it; TD-MPC is refused by lerobot
    itself in its own words (it takes one camera, the quick run's owners have two)."""
    from zk0.bench.policies import main

    assert main(["--types", "act", "tdmpc", "--json", str(tmp_path / "policies.json")]) == 0
    act, tdmpc = json.loads((tmp_path / "policies.json").read_text())["rows"]
    assert act == act | {"type": "act", "builds": True, "parameters": 12_308_102, "federated": True}
    assert tdmpc["builds"] is False and tdmpc["reason"].startswith("ValueError: TDMPCConfig handles at most one image")
    printed = capsys.readouterr().out
    assert "act        yes" in printed and "federated (policy='act')" in printed and "tdmpc      no" in printed


def sim_run_config(policy: str, rounds: int) -> str:
    """Two simulated owners and one closed-loop episode of 30 steps a round: short, but every path."""
    return (
        f"policy='{policy}' registry='{SIM_REGISTRY}' server-eval-dataset='sim-so101-eval' sim-eval-episodes=1 "
        "sim-episode-length=30 "
        f"num-server-rounds={rounds} local-steps=2 batch-size=2 eval-batches=1 checkpoint-interval=1"
    )


def federate(flower_env, run_config: str, out: Path, name: str) -> tuple[Path, str]:
    """One `flwr run` of two simulated owners: its run folder and what it printed, every owner
    having built ``name``."""
    from zk0.deployment.simulation import cpu_federation, flwr_run

    for entry in load_registry(SIM_REGISTRY).entries:
        ensure_dataset(entry.name)
    log = flwr_run(flower_env, f"{run_config} output-dir='{out}'", cpu_federation(2, actors=1))
    runs = list(out.iterdir()) if out.exists() else []
    assert len(runs) == 1, log[-3000:]
    assert f"[zk0] Model: tiny {name} (" in log, log[-3000:]
    for client in ("client_0", "client_1"):
        assert f"and built {name} (" in (runs[0] / "clients" / client / "client.log").read_text()
    return runs[0], log


def loads_in_lerobot(best: Path, policy: str, class_name: str, tmp_path: Path) -> None:
    """The checkpoint is ``policy`` to lerobot's own loader, offline, and `lerobot-eval` rolls it
    out in zk0's env."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    config = PreTrainedConfig.from_pretrained(best)
    assert config.type == policy and config.pretrained_backbone_weights is None, "it loads offline"
    assert type(get_policy_class(config.type).from_pretrained(best)).__name__ == class_name
    done = subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={best}", "--env.type=zk0_so101",
         "--env.episode_length=20", "--eval.n_episodes=1", "--eval.batch_size=1", "--policy.device=cpu",
         f"--rename_map={json.dumps(SIM_CAMERAS)}", f"--output_dir={tmp_path / 'lerobot-eval'}"],
        capture_output=True, text=True, timeout=600, check=False, env={**os.environ, "MUJOCO_GL": "egl"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((tmp_path / "lerobot-eval" / "eval_info.json").read_text())["overall"]["n_episodes"] == 1


@pytest.mark.e2e
@pytest.mark.allowance(420)
def test_an_act_federation_rolls_out_checkpoints_continues_and_loads_in_lerobot(flower_env, tmp_path):
    """Two simulated owners train ACT from their frames for two rounds through `flwr run`, with
    personal models and closed-loop evaluation; the checkpoint is ACT to lerobot's own loader and
    `lerobot-eval` rolls it out in zk0's env; resumed after round 1, the run ends with the same model."""
    from safetensors.torch import load_file

    from zk0.deployment.simulation import cpu_federation, flwr_run

    run_config = f"{sim_run_config('act', rounds=2)} personal-steps=1"
    run_dir, log = federate(flower_env, run_config, tmp_path / "outputs", "ACT")
    assert "Round 2/2: 2 clients trained" in log and "Personal models after round 2" in log
    loads_in_lerobot(run_dir / "models" / "best", "act", "ACTPolicy", tmp_path)

    final = load_file(run_dir / "models" / "checkpoint_round_2" / "model.safetensors")
    interrupted = tmp_path / "resumed" / run_dir.name  # as an interruption after round 1's checkpoint leaves it
    shutil.copytree(run_dir, interrupted)
    shutil.rmtree(interrupted / "models" / "checkpoint_round_2")
    for state in interrupted.glob("clients/*/trainer_state/round_2.safetensors"):
        state.unlink()
    log = flwr_run(
        flower_env, f"{run_config} output-dir='{interrupted.parent}' resume-from='{interrupted}'", cpu_federation(2, actors=1)
    )
    resumed = load_file(interrupted / "models" / "checkpoint_round_2" / "model.safetensors")
    assert all(torch.equal(resumed[name], final[name]) for name in final), log[-3000:]


@pytest.mark.e2e
@pytest.mark.allowance(300)
def test_a_diffusion_federation_rolls_out_from_two_observations_and_loads_in_lerobot(flower_env, tmp_path):
    """Two simulated owners train Diffusion Policy through `flwr run`: the server rolls the global
    model out (every step observed: it remembers two) and judges it on held-out frames, report.html
    gives the rollout command, the model card installs Diffusion's extra, the checkpoint is
    Diffusion Policy to lerobot's loader and `lerobot-eval`, each owner fine-tunes a personal
    model and rolls both out in its own set-up, and `zk0 export` hands an owner the global and the
    personal model, each one lerobot loads. (ACT's test resumes.)"""
    run_config = f"{sim_run_config('diffusion', rounds=1)} personal-steps=1 hf-repo-id='zk0-tests/diffusion'"
    run_dir, log = federate(flower_env, run_config, tmp_path / "outputs", "Diffusion Policy")
    assert "Personal models after round 1" in log and "success in the owner's own conditions" in log, log[-3000:]
    said = r"client 0 \d+% \[\d+, \d+\] of 1 -> \d+% \[\d+, \d+\] of 1, run the global model \(no difference"
    assert re.search(said, log), "with one episode each, no difference is beyond the noise"
    history = json.loads((run_dir / "server" / "metrics_history.json").read_text())
    for record in history["rounds"]:  # round 0 (the random start) and round 1
        judged = record["server-evaluate"]
        assert judged["episodes"] == 1 and 1 <= judged["episode-length"] <= 30 and judged["action-mse"] > 0, judged
    loads_in_lerobot(run_dir / "models" / "best", "diffusion", "DiffusionPolicy", tmp_path)
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    from zk0.cli import main

    assert main(["export", str(run_dir), "--client", "1", "--out", str(tmp_path / "owner-1")]) == 0
    assert DiffusionPolicy.from_pretrained(tmp_path / "owner-1").config.n_obs_steps == 2
    assert main(["export", str(run_dir), "--client", "0", "--personal", "--out", str(tmp_path / "personal-0")]) == 0
    assert DiffusionPolicy.from_pretrained(tmp_path / "personal-0").config.n_obs_steps == 2
    assert f"--policy.path={run_dir / 'models' / 'best'}" in (run_dir / "report.html").read_text()
    (card,) = (run_dir / "hub").glob("best_round_*/README.md")
    assert 'pip install "lerobot[feetech,diffusion]==0.6.1"' in card.read_text()
