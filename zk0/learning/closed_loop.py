"""Closed-loop evaluation: a policy drives the simulated SO-101, judged by its success rate.

The server rolls the global model out on the same seeded episodes every evaluated round, in
the conditions of its evaluation set; the study rolls every model out in each owner's conditions
too. Each rate comes with its episode count and 95% interval (zk0.learning.rates), and the per-episode
outcomes are kept so that two models on the same episodes can be compared pairwise.

The loop is lerobot's ``rollout`` (``lerobot.scripts.lerobot_eval``) with the work nobody reads
taken out. SmolVLA predicts a chunk of ``n_action_steps`` actions from one observation and plays
them back, so the cameras are rendered and the observation preprocessed only at the steps that
start a chunk (nine of ten rendered frames were never read), and the policy is asked for a chunk
with ``predict_action_chunk`` once per chunk rather than ``select_action`` every step (which
also walked every module for ``eval()`` each time). A policy that conditions on several past
observations (Diffusion Policy's ``n_obs_steps``) sees every step and is asked through
``select_action`` every step, exactly as ``rollout`` asks it. Everything else is lerobot's path, in its
order: ``preprocess_observation``, the task text, the env's and the policy's processors, the
batch of episodes seeded ``seed, seed + 1, ...`` and stepped together (as ``eval_policy`` with a
vector env of ``batch`` envs), the postprocessors on every action, ``is_success`` checked after
every step. tests/test_closed_loop.py holds it to ``eval_policy`` action for action.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.utils.constants import ACTION
from lerobot.utils.io_utils import write_video

from zk0.learning.policy import PolicyBundle, rng_devices
from zk0.learning.rates import rate_metrics
from zk0.sim.env import PickCubeEnv
from zk0.sim.lerobot_env import PickCubeEnvConfig
from zk0.sim.tasks import EPISODE_S, SIM_SPECS

GRADES = ("reached", "grasped", "lifted")
BATCH = 10  # episodes stepped together, one chunk inference for all of them (lerobot's eval.batch_size)


@dataclass
class Episode:
    """How one seeded episode went, and the actions it took (lerobot units)."""

    seed: int
    kind: str  # the task it was asked to do
    success: bool
    reached: bool
    grasped: bool
    lifted: bool
    steps: int
    actions: np.ndarray = field(repr=False)
    placed: bool = False  # a task that moves a cube somewhere: a lifted cube rested there (zk0.sim.env)


class ClosedLoop:
    """The seeded episodes of one set of conditions (of each task, in a multi-task set-up); the envs
    are built once for the run, and ``close()`` releases their renderers."""

    def __init__(
        self, conditions: str, episodes: int, seed: int, height: int, width: int,
        episode_length: int = PickCubeEnvConfig.episode_length, batch: int = BATCH,
    ):  # fmt: skip
        self.config = PickCubeEnvConfig(
            conditions=conditions, observation_height=height, observation_width=width, episode_length=episode_length
        )
        self.env_preprocessor, self.env_postprocessor = self.config.get_env_processors()
        self.batch = min(batch, episodes)  # episodes stepped together, each task's apart
        self.envs = {
            task.kind: [PickCubeEnv(task, height, width) for _ in range(self.batch)]
            for task in SIM_SPECS[conditions].tasks
        }
        self.episodes, self.seed = episodes, seed

    def episode_length(self, kind: str) -> int:
        """Steps before an episode of ``kind`` ends unsolved: the run's, for as long as a pick-up may
        run (a sort, two carries, gets twice as many)."""
        return round(self.config.episode_length * EPISODE_S[kind] / EPISODE_S["pick"])

    def __call__(self, bundle: PolicyBundle, video: Path | None = None) -> dict[str, float]:
        """Success with its interval, graded rates and mean length over the seeded episodes (and
        each task's, in a multi-task set-up); the first one's video written to ``video`` when given."""
        started = time.perf_counter()
        metrics = summary(self.rollouts(bundle, video))
        metrics["sim-eval-s"] = time.perf_counter() - started
        return metrics

    def rollouts(self, bundle: PolicyBundle, video: Path | None = None) -> list[Episode]:
        """Every episode, task by task, in seed order (each task's episodes seeded alike). The
        policy's noise is drawn from a generator seeded with the run's seed (and the caller's random
        state left as it was), so a model meets the same noise on the same episodes every time it is
        evaluated. The policy acts in eval mode, as in lerobot's ``eval_policy`` (no dropout), and is
        left in the mode it was in."""
        frames: list[np.ndarray] | None = [] if video else None
        done: list[Episode] = []
        training = bundle.policy.training
        bundle.policy.eval()
        with torch.random.fork_rng(devices=rng_devices(bundle)):
            torch.manual_seed(self.seed)
            for envs in self.envs.values():
                for first in range(0, self.episodes, len(envs)):
                    seeds = range(self.seed + first, self.seed + min(first + len(envs), self.episodes))
                    done += self._batch(bundle, envs, list(seeds), frames if not done else None)
        bundle.policy.train(training)  # ACT's predict_action_chunk itself switches to eval mode
        if video and frames:
            video.parent.mkdir(parents=True, exist_ok=True)
            write_video(str(video), np.stack(frames), self.config.fps)
        return done

    def _batch(
        self, bundle: PolicyBundle, envs: list[PickCubeEnv], seeds: list[int], frames: list[np.ndarray] | None
    ) -> list[Episode]:
        """One batch of episodes of one task stepped together until each has succeeded or run out of time."""
        envs = envs[: len(seeds)]
        kind, length = envs[0].task.kind, self.episode_length(envs[0].task.kind)
        bundle.policy.reset()
        observations = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds, strict=True)]
        if frames is not None:
            frames.append(envs[0].render())
        ended: list[Episode | None] = [None] * len(envs)
        actions: list[list[np.ndarray]] = [[] for _ in envs]
        chunk: deque[torch.Tensor] = deque()
        history = getattr(bundle.policy.config, "n_obs_steps", 1) > 1
        for step in range(length):
            if all(e is not None for e in ended):
                break
            if history or not chunk:  # only now is what the cameras see read
                if step:
                    running = zip(envs, observations, ended, strict=True)
                    observations = [env.observe() if e is None else o for env, o, e in running]
                if history:  # a policy that remembers past observations (Diffusion's) sees every one
                    chunk.append(self._select(bundle, envs, observations))
                else:
                    chunk.extend(self._predict(bundle, envs, observations))
            action = self._postprocess(bundle, chunk.popleft())
            for i, env in enumerate(envs):
                if ended[i]:
                    continue  # as lerobot's rollout masks a finished episode's later steps
                _, success = env.act(action[i])
                actions[i].append(action[i])
                if frames is not None and i == 0:
                    frames.append(env.render())  # the video's episode: every step, as lerobot records it
                if success or env.steps >= length:
                    ended[i] = Episode(seeds[i], kind, success, **{g: env.outcome[g] for g in GRADES}, steps=env.steps,
                                       actions=np.stack(actions[i]), placed=env.outcome.get("placed", False))  # fmt: skip
        return [e for e in ended if e is not None]

    def _observation(self, bundle: PolicyBundle, envs: Sequence[PickCubeEnv], observations: list[dict]) -> dict:
        """Every env's observation as ``rollout`` prepares a vector env's, through the processors."""
        stacked = {
            "pixels": {cam: np.stack([o["pixels"][cam] for o in observations]) for cam in observations[0]["pixels"]},
            "agent_pos": np.stack([o["agent_pos"] for o in observations]),
        }
        observation = preprocess_observation(stacked)
        observation["task"] = [env.task_description for env in envs]
        return bundle.preprocessor(self.env_preprocessor(observation))

    def _predict(self, bundle: PolicyBundle, envs: Sequence[PickCubeEnv], observations: list[dict]) -> list:
        """The next chunk of actions for every env."""
        observation = self._observation(bundle, envs, observations)
        with torch.inference_mode():
            actions = bundle.policy.predict_action_chunk(observation)
        return list(actions.transpose(0, 1)[: bundle.policy.config.n_action_steps])

    def _select(self, bundle: PolicyBundle, envs: Sequence[PickCubeEnv], observations: list[dict]) -> torch.Tensor:
        """The next action for every env from ``select_action``, which keeps the policy's own queue
        of observations and of the chunk it plays, as lerobot's ``rollout`` asks every step."""
        observation = self._observation(bundle, envs, observations)
        with torch.inference_mode():
            return bundle.policy.select_action(observation)

    def _postprocess(self, bundle: PolicyBundle, action: torch.Tensor) -> np.ndarray:
        action = bundle.postprocessor(action)
        return self.env_postprocessor({ACTION: action})[ACTION].to("cpu").numpy()

    def close(self) -> None:
        for envs in self.envs.values():
            for env in envs:
                env.close()


def summary(episodes: Sequence[Episode]) -> dict[str, float]:
    """Success rate with its 95% interval and episode count, each grade's rate (``placed-rate`` over
    the episodes of tasks that move a cube somewhere), the mean length; in a multi-task set-up the
    same for each task (``place-success-rate``, ``place-episodes``, ...)
    beside those over every episode."""
    metrics = _rates(episodes)
    kinds = list(dict.fromkeys(e.kind for e in episodes))
    if len(kinds) > 1:
        for kind in kinds:
            metrics |= {f"{kind}-{k}": v for k, v in _rates([e for e in episodes if e.kind == kind]).items()}
    return metrics


def _rates(episodes: Sequence[Episode]) -> dict[str, float]:
    metrics = rate_metrics([e.success for e in episodes])
    metrics |= {f"{grade}-rate": float(np.mean([getattr(e, grade) for e in episodes])) for grade in GRADES}
    if placing := [e for e in episodes if e.kind != "pick"]:  # the funnel's fourth grade, where there is one
        metrics["placed-rate"] = float(np.mean([e.placed for e in placing]))
    metrics["episode-length"] = float(np.mean([e.steps for e in episodes]))
    return metrics
