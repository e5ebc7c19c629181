"""Closed-loop evaluation: the global policy drives the simulated SO-101, judged by success rate.

The server rolls the policy out with lerobot's own ``eval_policy`` (so SmolVLA's action
chunking, ``n_action_steps``, runs exactly as lerobot runs it) on the same seeded episodes
every evaluated round, in the conditions of the server's evaluation set. Besides lerobot's
success rate it reports the graded outcome the env keeps (reached, grasped, lifted) and the
mean episode length, and saves the first episode as a video.
"""

from __future__ import annotations

import io
import shutil
import time
from contextlib import redirect_stderr
from pathlib import Path

import numpy as np
from lerobot.envs.factory import make_env
from lerobot.scripts.lerobot_eval import eval_policy

from zk0.policy import PolicyBundle
from zk0.sim.lerobot_env import PickCubeEnvConfig

GRADES = ("reached", "grasped", "lifted")


def quiet_progress_bars():
    """lerobot's rollout draws a tqdm bar on stderr per step, always enabled outside SLURM (its
    explicit ``disable=`` overrides tqdm's ``TQDM_DISABLE``); a server log has no use for them."""
    return redirect_stderr(io.StringIO())


class ClosedLoop:
    """One vector env built once for the run; ``close()`` releases its renderer."""

    def __init__(self, conditions: str, episodes: int, seed: int, height: int, width: int):
        self.config = PickCubeEnvConfig(conditions=conditions, observation_height=height, observation_width=width)
        self.env = make_env(self.config)[self.config.type][0]
        self.env_preprocessor, self.env_postprocessor = self.config.get_env_processors()
        self.episodes, self.seed = episodes, seed

    def __call__(self, bundle: PolicyBundle, video: Path | None = None) -> dict[str, float]:
        """Success, graded rates and mean length over the seeded episodes; the first one's video
        written to ``video`` when given."""
        started = time.perf_counter()
        sim = self.env.envs[0].unwrapped
        sim.finished.clear()
        videos = video.parent / f".{video.stem}-frames" if video else None
        with quiet_progress_bars():
            result = eval_policy(
                self.env,
                bundle.policy,
                self.env_preprocessor,
                self.env_postprocessor,
                bundle.preprocessor,
                bundle.postprocessor,
                n_episodes=self.episodes,
                max_episodes_rendered=1 if video else 0,
                videos_dir=videos,
                start_seed=self.seed,
            )
        if video and result.get("video_paths"):
            shutil.move(result["video_paths"][0], video)
            shutil.rmtree(videos, ignore_errors=True)
        episodes = sim.finished[: self.episodes]
        metrics = {"success-rate": float(np.mean([e["success"] for e in episodes]))}
        metrics |= {f"{grade}-rate": float(np.mean([e[grade] for e in episodes])) for grade in GRADES}
        metrics["episode-length"] = float(np.mean([e["steps"] for e in episodes]))
        metrics["sim-eval-s"] = time.perf_counter() - started
        return metrics

    def close(self) -> None:
        self.env.close()
