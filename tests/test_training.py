"""Local training through lerobot's update_policy, the FedProx term, the schedule, evaluation."""

from __future__ import annotations

import dataclasses
import math
import shutil
import time

import pytest
import torch
from lerobot.optim import CosineDecayWithWarmupSchedulerConfig, DiffuserSchedulerConfig

from zk0.config import RunConfig
from zk0.data.loaders import eval_loader, open_metadata, open_split, train_loader
from zk0.learning.policy import PolicyError, backbone_fingerprint, build_policy, get_trainable, set_trainable
from zk0.learning.training import FedProx, LocalTrainer, TrainingError, evaluate, set_schedule_step


def test_twenty_update_policy_steps_lower_the_loss(client_parts):
    bundle, split, trainer = client_parts
    fixed = eval_loader(split.train, trainer.run)  # training frames, fixed order, seeded noise
    before = evaluate(bundle, split, fixed, max_batches=3, seed=0, max_skip=0.1)["policy-loss"]
    started = time.perf_counter()
    metrics = trainer.fit(steps=20, mu=0.0, global_step=0)
    wall = time.perf_counter() - started
    after = evaluate(bundle, split, fixed, max_batches=3, seed=0, max_skip=0.1)["policy-loss"]
    assert metrics["num-examples"] == 20 * trainer.run.batch_size
    assert metrics["skipped-batches"] == 0 and 0 < metrics["step-time"] * 20 <= wall
    assert after < 0.9 * before, (before, after)


def test_a_time_budget_ends_the_round_after_the_step_that_reaches_it(client_parts):
    """``local-time-s``: at least one step however short the budget, at most ``local-steps``
    however long, and the steps taken reported; the schedule moves on by the steps taken."""
    bundle, split, trainer = client_parts
    short = trainer.fit(steps=50, mu=0.0, global_step=0, budget_s=1e-9)
    assert short["local-steps"] == 1 and short["num-examples"] == trainer.run.batch_size
    assert trainer.scheduler.last_epoch == 1
    long = trainer.fit(steps=3, mu=0.0, global_step=50, budget_s=3600.0)
    assert long["local-steps"] == 3 and trainer.scheduler.last_epoch == 53
    assert trainer.fit(steps=2, mu=0.0, global_step=53)["local-steps"] == 2  # no budget: every step


def test_fedprox_gradient_is_mu_times_distance_to_global():
    weight = torch.nn.Parameter(torch.tensor([1.0, -2.0, 3.0]))
    prox = FedProx({"w": weight})
    prox.anchor_at(mu=0.5)
    delta = torch.tensor([0.2, 0.4, -1.0])
    with torch.no_grad():
        weight.add_(delta)
    (weight * 0).sum().backward()  # a loss with zero gradient: only the proximal term remains
    torch.testing.assert_close(weight.grad, 0.5 * delta)
    assert prox.loss() == pytest.approx(0.5 / 2 * float((delta**2).sum()))


def test_fedprox_adds_its_gradient_to_the_policy_loss_gradient(client_parts):
    bundle, split, trainer = client_parts
    name = bundle.trainable_names[0]
    param = dict(bundle.policy.named_parameters())[name]
    trainer.fedprox.anchor_at(mu=0.0)
    with torch.no_grad():
        param.add_(0.1)
    (param.sum() * 2).backward()
    plain = param.grad.clone()
    param.grad = None
    trainer.fedprox.mu = 0.3
    (param.sum() * 2).backward()
    torch.testing.assert_close(param.grad - plain, torch.full_like(plain, 0.3 * 0.1), rtol=1e-4, atol=1e-6)
    param.grad = None


@pytest.mark.parametrize("preset", ["smolvla", "diffusion"])
def test_schedule_follows_the_global_step_not_the_round(preset):
    """A client sampled again, or a resumed run, puts the schedule at the run's global step: SmolVLA's
    warm-up and cosine decay, and Diffusion Policy's (diffusers' cosine, its rate the optimizer's)."""

    def scheduler():
        opt = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=1e-4)
        if preset == "diffusion":
            return DiffuserSchedulerConfig(name="cosine", num_warmup_steps=10).build(opt, 100)
        cfg = CosineDecayWithWarmupSchedulerConfig(
            peak_lr=1e-4, decay_lr=1e-6, num_warmup_steps=10, num_decay_steps=100
        )
        return cfg.build(opt, 100)

    stepped, jumped = scheduler(), scheduler()
    for _ in range(25):
        stepped.optimizer.step()
        stepped.step()
    set_schedule_step(jumped, 25)
    assert jumped.optimizer.param_groups[0]["lr"] == pytest.approx(stepped.optimizer.param_groups[0]["lr"])
    assert jumped.get_last_lr() == pytest.approx(stepped.get_last_lr())


def test_client_resumes_the_schedule_in_later_rounds(client_parts):
    _, _, trainer = client_parts
    trainer.fit(steps=2, mu=0.01, global_step=0)
    assert trainer.scheduler.last_epoch == 2
    trainer.fit(steps=2, mu=0.01, global_step=6)  # round 4 of a 2-step run, sampled again
    assert trainer.scheduler.last_epoch == 8


def test_evaluation_is_seeded_and_reports_unnormalised_mse(client_parts):
    bundle, split, trainer = client_parts
    loader = eval_loader(split.evaluation, trainer.run)
    runs = []
    for _ in range(2):
        started = time.perf_counter()
        runs.append(evaluate(bundle, split, loader, max_batches=2, seed=3, max_skip=0.1))
        assert 0 < runs[-1].pop("eval-s") <= time.perf_counter() - started
    first, second = runs
    assert first == second
    assert first["num-examples"] == 2 * trainer.run.batch_size
    assert first["action-mse"] > 1.0  # joint positions in degrees, not normalised units


def test_only_trainable_parameters_travel_and_backbones_match(registry, client_parts):
    bundle, _, _ = client_parts
    arrays = get_trainable(bundle)
    trainable = {n for n, p in bundle.policy.named_parameters() if p.requires_grad}
    assert set(arrays.keys()) == trainable
    assert len(trainable) < len(list(bundle.policy.parameters()))
    entry = registry.get("synth-so100-eval")
    server = build_policy(RunConfig(), open_metadata(entry), entry, registry.model_cameras())
    assert backbone_fingerprint(server) == backbone_fingerprint(bundle)
    other = build_policy(RunConfig(seed=7), open_metadata(entry), entry, registry.model_cameras())
    assert backbone_fingerprint(other) != backbone_fingerprint(bundle)
    set_trainable(server, arrays)
    for name, value in get_trainable(server).items():
        assert (value.numpy() == arrays[name].numpy()).all()
    del arrays[bundle.trainable_names[0]]
    with pytest.raises(PolicyError, match="do not match"):
        set_trainable(server, arrays)


def test_undecodable_video_fails_the_round_with_a_clear_error(tmp_path, registry):
    entry = registry.clients[0]
    copy = tmp_path / "broken"
    shutil.copytree(entry.local_root(), copy)
    for video in copy.rglob("*.mp4"):
        video.write_bytes(video.read_bytes()[:200])
    broken = dataclasses.replace(entry, synthetic=False, root=str(copy))
    run = RunConfig(batch_size=4)
    meta = open_metadata(broken)
    bundle = build_policy(run, meta, broken, registry.model_cameras())
    split = open_split(broken, meta, bundle.policy.config, run)
    trainer = LocalTrainer(bundle, split, train_loader(split.train, run, bundle.device), run)
    with pytest.raises(TrainingError, match="could not be decoded, more than max-skip-fraction=0.1"):
        trainer.fit(steps=2, mu=0.0, global_step=0)


def test_a_fresh_process_continues_the_data_order_and_the_optimizer(client_parts):
    bundle, split, trainer = client_parts
    trainer.fit(steps=3, mu=0.0, global_step=0)
    record, seen = trainer.optimizer_record(), trainer.batches_seen
    assert seen == 3 and len(record) > 0
    fresh = LocalTrainer(bundle, split, train_loader(split.train, trainer.run, bundle.device), trainer.run)
    fresh.restore(seen, record)
    assert fresh._next_batch()["index"].tolist() == trainer._next_batch()["index"].tolist()
    before, after = trainer.optimizer.state_dict()["state"], fresh.optimizer.state_dict()["state"]
    assert before.keys() == after.keys()
    for index, state in before.items():
        torch.testing.assert_close(after[index]["exp_avg_sq"], state["exp_avg_sq"])


def test_a_stale_session_catches_up_with_a_newer_one(client_parts):
    bundle, split, stale = client_parts
    stale.fit(steps=1, mu=0.0, global_step=0)  # its iterator is open at batch 1
    newer = LocalTrainer(bundle, split, train_loader(split.train, stale.run, bundle.device), stale.run)
    newer.fit(steps=4, mu=0.0, global_step=0)
    stale.restore(newer.batches_seen, newer.optimizer_record())
    assert stale._next_batch()["index"].tolist() == newer._next_batch()["index"].tolist()


@pytest.mark.slow
def test_a_compiled_policy_keeps_fedprox_and_its_compiled_code(registry, monkeypatch):
    """``compile = true``: lerobot compiles SmolVLA's forward; FedProx's hooks still reach every
    trainable gradient, and the compiled code goes to $ZK0_CACHE/inductor for later processes."""
    import os

    from zk0.common.cache import default_cache_root
    from zk0.data.loaders import prepare_batch
    from zk0.federation.client import build_client

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", "unset")  # recorded, so the test's end restores it
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR")
    client = build_client(
        RunConfig(compile=True, batch_size=2, local_steps=1), registry.clients[0], registry.model_cameras()
    )
    policy, split = client.bundle.policy, client.split
    assert policy.config.compile_model and policy.config.compile_mode == "default"
    batch = client.bundle.preprocessor(
        prepare_batch(next(iter(client.trainer.loader)), split.meta.camera_keys, split.entry.task, client.bundle.device)
    )
    params = {n: p for n, p in policy.named_parameters() if n in client.bundle.trainable_names}
    client.trainer.fedprox.anchor_at(mu=0.0)
    with torch.no_grad():
        for param in params.values():
            param.add_(0.01)

    def gradients(mu: float) -> dict[str, torch.Tensor]:
        client.trainer.fedprox.mu = mu
        policy.zero_grad(set_to_none=True)
        torch.manual_seed(0)
        loss, _ = policy.forward(batch)
        loss.backward()
        return {n: p.grad.clone() for n, p in params.items() if p.grad is not None}

    plain, proximal = gradients(0.0), gradients(0.5)
    assert len(plain) > len(params) // 2, "the compiled forward reaches the trainable parameters"
    for name, grad in plain.items():
        torch.testing.assert_close(proximal[name] - grad, torch.full_like(grad, 0.5 * 0.01), rtol=1e-3, atol=1e-5)
    moved = sum(p.numel() for p in params.values())  # every trainable weight is 0.01 from the anchor
    assert client.trainer.fedprox.loss() == pytest.approx(0.5 / 2 * 0.01**2 * moved, rel=1e-3)
    cache = default_cache_root() / "inductor"
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(cache) and any(cache.rglob("*.py")), "compiled code kept"


def test_image_transforms_are_lerobots_on_training_frames_only(registry):
    """``image-transforms``: lerobot's own ImageTransforms, drawn per frame, on the batches the client
    trains on; the frames stay frames (shape, [0, 1]); evaluation is never augmented (the same
    figures as a client without transforms, from the same starting weights)."""
    from lerobot.transforms.transforms import ImageTransforms

    from zk0.config import from_run_config
    from zk0.data.loaders import prepare_batch
    from zk0.federation.client import build_client
    from zk0.learning.augmentation import augment
    from zk0.learning.training import evaluate

    keys = {"batch-size": 4, "eval-batches": 1}
    augmented_client = build_client(
        from_run_config({**keys, "image-transforms": True, "image-transforms-max": 6, "image-transforms-brightness": 0.6}),
        registry.clients[0], registry.model_cameras(),
    )  # fmt: skip
    plain_client = build_client(from_run_config(keys), registry.clients[0], registry.model_cameras())
    trainer, meta = augmented_client.trainer, augmented_client.split.meta
    assert isinstance(trainer.transforms, ImageTransforms) and plain_client.trainer.transforms is None
    assert trainer.transforms.transforms["brightness"].brightness == pytest.approx((0.4, 1.6))

    batch = next(iter(trainer.loader))
    key = meta.camera_keys[0]
    plain = prepare_batch(dict(batch), meta.camera_keys, None, trainer.bundle.device)[key].clone()
    augmented = augment(prepare_batch(dict(batch), meta.camera_keys, None, trainer.bundle.device),
                        meta.camera_keys, trainer.transforms)[key]  # fmt: skip
    assert augmented.shape == plain.shape and 0.0 <= augmented.min() and augmented.max() <= 1.0
    assert all(not torch.equal(a, p) for a, p in zip(augmented, plain, strict=True)), "every frame changes"
    assert not torch.equal(augmented[0] - plain[0], augmented[1] - plain[1]), "each frame has its own draw"

    def judged(session):
        return evaluate(session.bundle, session.split, session.eval_batches, 1, 0, 1.0)["action-mse"]

    assert judged(augmented_client) == judged(plain_client)
    assert math.isfinite(trainer.fit(2, 0.0, global_step=0)["train-loss"]), "the client trains on augmented frames"
