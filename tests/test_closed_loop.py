"""zk0's closed loop against lerobot's own ``rollout``: the same episodes, action for action, while
rendering only the frames a chunking policy reads; success rates with their intervals."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lerobot.envs.factory import make_env
from lerobot.scripts.lerobot_eval import rollout

from zk0.config import from_run_config
from zk0.data.assets import ensure_dataset
from zk0.data.loaders import open_metadata
from zk0.data.registry import load_registry
from zk0.learning.closed_loop import ClosedLoop, summary
from zk0.learning.policy import build_policy
from zk0.learning.rates import wilson

REGISTRY = "configs/sim-registry.toml"
CONDITIONS = "sim-so101-eval"
TASKS_REGISTRY = "configs/sim-tasks-registry.toml"


def untrained(policy: str):
    """An untrained tiny-128 policy with the server set's statistics: its actions wander, so two
    paths that differ anywhere part ways at once."""
    registry = load_registry(REGISTRY)
    entry = registry.get(CONDITIONS)
    ensure_dataset(entry.name)
    run = from_run_config({"registry": REGISTRY, "server-eval-dataset": CONDITIONS, "model": "tiny-128", "policy": policy})
    return build_policy(run, open_metadata(entry), entry, registry.model_cameras())


@pytest.fixture(scope="module")
def bundle():
    return untrained("smolvla")


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["smolvla", "diffusion"])
def test_the_fast_loop_takes_lerobots_actions_in_every_episode(policy):
    """Four seeded episodes of 100 steps in batches of two: lerobot's ``rollout`` over a vector env of two (as
    ``eval_policy`` runs it, every frame rendered and ``select_action`` every step) and zk0's loop
    take the same actions at every step and end the same way: SmolVLA asked once a chunk,
    Diffusion Policy (two observations remembered) every step."""
    bundle = untrained(policy)
    seed, episodes, batch = 11, 4, 2
    loop = ClosedLoop(CONDITIONS, episodes, seed, 128, 128, episode_length=100, batch=batch)
    env = make_env(loop.config, n_envs=batch)[loop.config.type][0]
    try:
        ours = loop.rollouts(bundle)
        theirs = []
        torch.manual_seed(seed)  # the loop seeds the policy's noise so
        for first in range(0, episodes, batch):
            data = rollout(env, bundle.policy, loop.env_preprocessor, loop.env_postprocessor, bundle.preprocessor,
                           bundle.postprocessor, seeds=list(range(seed + first, seed + first + batch)))  # fmt: skip
            for i in range(batch):
                last = int(torch.argmax(data["done"][i].to(int)))
                theirs.append((data["action"][i, : last + 1].numpy(), bool(data["success"][i, : last + 1].any())))
    finally:
        env.close()
        loop.close()
    assert [e.seed for e in ours] == list(range(seed, seed + episodes))
    for episode, (actions, success) in zip(ours, theirs, strict=True):
        assert episode.steps == len(actions) and episode.success == success
        np.testing.assert_array_equal(episode.actions, actions)
    assert np.ptp(np.concatenate([e.actions for e in ours]), axis=0).max() > 1.0, "the arm moved"


def test_a_rollout_reports_its_rate_with_the_interval_and_writes_the_first_video(bundle, tmp_path):
    """Three episodes of the untrained policy, cut at 60 steps: the rates carry their episode count
    and Wilson interval (0/3 is not [0, 0]), the first episode's video is written, and evaluating the
    same model again gives the same episodes (the noise is seeded, the caller's RNG untouched)."""
    loop = ClosedLoop(CONDITIONS, 3, 5, 128, 128, episode_length=60, batch=3)
    try:
        torch.manual_seed(0)
        before = torch.rand(1)
        torch.manual_seed(0)
        metrics = loop(bundle, tmp_path / "videos" / "round_1.mp4")
        assert torch.rand(1) == before, "the caller's random state is left as it was"
        again = loop.rollouts(bundle)
    finally:
        loop.close()
    assert metrics["episodes"] == 3 and metrics["success-rate"] == 0.0
    assert (metrics["success-low"], metrics["success-high"]) == pytest.approx(wilson(0, 3))
    assert metrics["success-high"] > 0.5 and metrics["episode-length"] == 60
    assert set(metrics) >= {"reached-rate", "grasped-rate", "lifted-rate", "sim-eval-s"}
    assert "placed-rate" not in metrics, "a pick-up places nothing"
    assert (tmp_path / "videos" / "round_1.mp4").stat().st_size > 1000
    assert summary(again) | {"sim-eval-s": metrics["sim-eval-s"]} == metrics


def test_a_multi_task_set_is_rolled_out_task_by_task_with_each_tasks_rate():
    """The server's multi-task set: each task's episodes seeded alike, each task's rate with its
    interval beside the rate over all of them, a sort given twice a pick-up's steps, and the console's
    words naming the worst task."""
    from zk0.learning.rates import per_task, rate_text, simulator_text
    from zk0.sim.tasks import KINDS

    registry = load_registry(TASKS_REGISTRY)
    entry = registry.server
    ensure_dataset(entry.name)
    run = from_run_config({"registry": TASKS_REGISTRY, "server-eval-dataset": entry.name, "model": "tiny-128"})
    bundle = build_policy(run, open_metadata(entry), entry, registry.model_cameras())
    loop = ClosedLoop(entry.name, 2, 3, 128, 128, episode_length=12, batch=2)
    try:
        episodes = loop.rollouts(bundle)
    finally:
        loop.close()
    assert [(e.kind, e.seed) for e in episodes] == [(kind, seed) for kind in KINDS for seed in (3, 4)]
    assert [e.steps for e in episodes] == [12] * 6 + [24] * 2, "nothing solved; a sort may run twice as long"
    metrics = summary(episodes)
    assert metrics["episodes"] == 8 and list(per_task(metrics)) == list(KINDS)
    assert all(per_task(metrics)[kind]["episodes"] == 2 for kind in KINDS)
    assert metrics["placed-rate"] == per_task(metrics)["sort"]["placed-rate"] == 0.0, "the funnel's fourth grade"
    assert "placed-rate" not in per_task(metrics)["pick"], "a pick-up places nothing"
    assert simulator_text(metrics) == (
        f"success {rate_text(0.0, 8)} in the simulator over 4 tasks (worst: pick, {rate_text(0.0, 2)})"
    )
