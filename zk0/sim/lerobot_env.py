"""The simulated SO-101's tasks as a lerobot ``EnvConfig`` (``--env.type=zk0_so101``), so lerobot's own
evaluation (``eval_policy``, ``rollout``, ``lerobot-eval``) runs a zk0 checkpoint on it.

Importing this module registers both the gymnasium id and the env config; lerobot imports
it itself (``package_name``) when it meets the id unregistered.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from zk0.sim.env import JOINTS, state_size
from zk0.sim.tasks import KINDS, SIM_SPECS, SimTask

GYM_TASK = "PickCube-v0"
GYM_ID = f"zk0/{GYM_TASK}"  # gymnasium ids allow no dots in the namespace, so not this module's name

if GYM_ID not in gym.registry:
    gym.register(id=GYM_ID, entry_point="zk0.sim.env:make_env")


@EnvConfig.register_subclass("zk0_so101")
@dataclass
class PickCubeEnvConfig(EnvConfig):
    """An SO-101 doing what the instruction says, in one recorded set-up's conditions
    (``conditions``: a name from ``zk0.sim.tasks.SIM_SPECS``; the server's evaluation set spans
    them all): the set-up's own task, or the ``kind`` given (pick, place, stack, sort)."""

    task: str | None = GYM_TASK
    fps: int = 30
    episode_length: int = 300
    conditions: str = "sim-so101-eval"
    kind: str | None = None  # the task, if not the set-up's own
    observation_height: int = 128
    observation_width: int = 128
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "pixels/front": f"{OBS_IMAGES}.front",
            "pixels/wrist": f"{OBS_IMAGES}.wrist",
        }
    )

    def __post_init__(self):
        if self.conditions not in SIM_SPECS:
            raise ValueError(
                f"--env.conditions got {self.conditions!r}; expected one of the recorded set-ups {SIM_SPECS.described()}."
            )
        if self.kind is not None and self.kind not in KINDS:
            raise ValueError(f"--env.kind got {self.kind!r}; expected one of {', '.join(KINDS)}.")
        image = PolicyFeature(type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3))
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(len(JOINTS),)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(state_size(self.sim_task),)),
            "pixels/front": image,
            "pixels/wrist": image,
        }

    @property
    def sim_task(self) -> SimTask:
        """The set-up's task, of the ``kind`` given."""
        task = SIM_SPECS[self.conditions].task
        return replace(task, kind=self.kind) if self.kind else task

    @property
    def package_name(self) -> str:
        """What lerobot imports when the gym id is not registered yet: this module."""
        return __name__

    @property
    def gym_id(self) -> str:
        return GYM_ID

    @property
    def gym_kwargs(self) -> dict:
        return {
            "conditions": self.conditions,
            "kind": self.kind,
            "height": self.observation_height,
            "width": self.observation_width,
            "max_episode_steps": self.episode_length,
        }
