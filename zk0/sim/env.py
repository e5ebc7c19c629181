"""``PickCubeEnv``: an SO-101 picking up a cube, in lerobot's SO-101 units, as a gymnasium env.

State and action are the six ``*.pos`` values a real SO-101 dataset records (lerobot's
``so101_follower`` with degrees): the five arm joints in degrees, zero at the middle of each
joint's range as in the MJCF's "new calibration", and the gripper from 0 (closed) to 100 (open).
The action is the joint targets the servos move to, as a leader arm commands them. The
observation is lerobot's env contract: ``pixels`` (``front`` and ``wrist`` cameras, uint8 HxWx3)
and ``agent_pos``; ``task_description`` names the cube to pick up. Every step's ``info`` carries
``is_success`` (lerobot 0.6.1's ``rollout`` counts a missing key as a success) and the episode's
graded outcome so far: reached, grasped, lifted. In a task with ``cube_in_state`` (a privileged
study setting) the state also carries the target cube's xy on the table in centimetres
(``cube.x``, ``cube.y``): eight values instead of six.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from zk0.sim import cannot_render, load_mujoco
from zk0.sim.scene import CUBE_HALF, JAW_PADS, build_spec
from zk0.sim.tasks import SIM_SPECS, SimTask

mujoco = load_mujoco()

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
CUBE_STATE = ("cube.x", "cube.y")  # the target cube's xy (cm), after the joints in a cube_in_state task's state
COLOURS = {
    "red": (0.85, 0.12, 0.12, 1.0),
    "green": (0.15, 0.7, 0.2, 1.0),
    "blue": (0.12, 0.3, 0.85, 1.0),
    "yellow": (0.9, 0.8, 0.1, 1.0),
}
# The arm's pose at every reset (lerobot units): raised over the table, gripper half open.
HOME = np.array([0.0, -40.0, 20.0, 75.0, 0.0, 30.0])
REACHED_M = 0.02  # grasp point this close to the cube's centre (or both pads on the cube) reaches it
LIFTED_M = 0.03  # cube this far above the table, held by both pads
HOLD_STEPS = 10  # lifted for this many steps in a row ends the episode as a success
APART_M = 0.06  # the cubes' centres at least this far apart at every reset


def open_renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """A renderer without shadows, reflections or skybox (a 10x cheaper frame on a CPU), or one
    sentence saying why this machine cannot render."""
    try:
        renderer = mujoco.Renderer(model, height, width)
    except Exception as err:  # EGL/OSMesa failures surface as several exception types
        raise cannot_render(err) from None
    for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX):
        renderer.scene.flags[flag] = 0
    return renderer


def state_size(task: SimTask) -> int:
    """How many values the task's state holds: the six joints, and the cube's xy if it is told."""
    return len(JOINTS) + (len(CUBE_STATE) if task.cube_in_state else 0)


def to_lerobot(qpos: np.ndarray, gripper_range: np.ndarray) -> np.ndarray:
    """MuJoCo joint angles (rad) -> lerobot SO-101 units (degrees; gripper 0-100)."""
    out = np.degrees(qpos).astype(np.float32)
    low, high = gripper_range
    out[5] = 100.0 * (qpos[5] - low) / (high - low)
    return out


def to_mujoco(values: np.ndarray, gripper_range: np.ndarray) -> np.ndarray:
    """lerobot SO-101 units -> MuJoCo joint angles (rad)."""
    out = np.radians(np.asarray(values, dtype=np.float64))
    low, high = gripper_range
    out[5] = low + (high - low) * float(values[5]) / 100.0
    return out


class PickCubeEnv(gym.Env):
    """Pick up the named cube. One model, built once; renderers closed by ``close()``."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, task: SimTask | None = None, height: int = 128, width: int = 128, render_mode="rgb_array"):
        self.task = task or SimTask()
        self.height, self.width, self.render_mode = height, width, render_mode
        self.metadata = {**self.metadata, "render_fps": self.task.fps}
        self.model = build_spec(self.task.look, self.task.distractor).compile()
        self.data = mujoco.MjData(self.model)
        self.joint_ids = [self.model.joint(name).qposadr[0] for name in JOINTS]
        self._cube_geom = self.model.geom("cube").id
        self._pad_geoms = np.array([self.model.geom(name).id for name in JAW_PADS])
        self.gripper_range = self.model.jnt_range[self.model.joint("gripper").id].copy()
        self.substeps = round(1.0 / (self.task.fps * self.model.opt.timestep))
        self.renderer: mujoco.Renderer | None = None
        limits = self.model.jnt_range[[self.model.joint(name).id for name in JOINTS]]
        low, high = (to_lerobot(limits[:, i], self.gripper_range) for i in (0, 1))
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)
        image = gym.spaces.Box(0, 255, (height, width, 3), np.uint8)
        self.observation_space = gym.spaces.Dict(
            {
                "pixels": gym.spaces.Dict({"front": image, "wrist": image}),
                "agent_pos": gym.spaces.Box(-np.inf, np.inf, (state_size(self.task),), np.float32),
            }
        )
        self.colour = self.task.colours[0]
        self.outcome = {"reached": False, "grasped": False, "lifted": False}
        self.steps = self._held = 0

    @property
    def task_description(self) -> str:
        return f"Pick up the {self.colour} cube"

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        rng = self.np_random
        colours = list(self.task.colours)
        self.colour = colours.pop(int(rng.integers(len(colours))))
        spots = self._spots(rng, 2 if self.task.distractor else 1)
        self._place("cube", spots[0], self.colour, rng)
        if self.task.distractor:
            other = colours[int(rng.integers(len(colours)))] if colours else "green"
            self._place("distractor", spots[1], other, rng)
        home = HOME + rng.normal(0.0, 2.0, size=6) * np.array([1, 1, 1, 1, 1, 0])
        self.data.qpos[self.joint_ids] = to_mujoco(home, self.gripper_range)
        self.data.ctrl[:] = self.data.qpos[self.joint_ids]
        mujoco.mj_step(self.model, self.data, nstep=50)  # let the cubes settle on the table
        self.outcome = {"reached": False, "grasped": False, "lifted": False}
        self.steps = self._held = 0
        return self.observe(), self._info()

    def step(self, action):
        reward, success = self.act(action)
        return self.observe(), reward, success, False, self._info(success)

    def act(self, action) -> tuple[float, bool]:
        """``step`` without the observation: the servos move to ``action`` for one control period.
        Returns the graded reward so far (0-3) and whether the cube has now been held up long
        enough (success, which ends the episode). zk0.learning.closed_loop renders only the steps a
        chunking policy reads, so it calls this and ``observe`` apart."""
        target = np.clip(np.asarray(action, dtype=np.float64), self.action_space.low, self.action_space.high)
        self.data.ctrl[:] = to_mujoco(target, self.gripper_range)
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        self.steps += 1
        lifted = self._grade()
        self._held = self._held + 1 if lifted else 0
        return float(sum(self.outcome.values())), self._held >= HOLD_STEPS

    def observe(self) -> dict:
        """The observation now: both cameras rendered, and the state."""
        state = self.joint_pos()
        if self.task.cube_in_state:
            state = np.concatenate([state, 100.0 * self.cube_pos()[:2]]).astype(np.float32)
        return {"pixels": self._images(), "agent_pos": state}

    def render(self) -> np.ndarray:
        """The front and wrist cameras side by side (what a rollout video shows)."""
        images = self._images()
        return np.concatenate([images["front"], images["wrist"]], axis=1)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    # The task's state, in MuJoCo's units (the scripted expert reads it; a policy never does).
    def cube_pos(self, name: str = "cube") -> np.ndarray:
        return self.data.body(name).xpos.copy()

    def cube_yaw(self) -> float:
        w, x, y, z = self.data.body("cube").xquat
        return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))

    def joint_pos(self) -> np.ndarray:
        """The joints now, in lerobot units."""
        return to_lerobot(self.data.qpos[self.joint_ids], self.gripper_range)

    def _place(self, name: str, xy: np.ndarray, colour: str, rng) -> None:
        joint = self.model.joint(name)
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        self.data.qpos[joint.qposadr[0] : joint.qposadr[0] + 7] = [*xy, CUBE_HALF, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self.model.geom_rgba[self.model.geom(name).id] = COLOURS[colour]

    def _spots(self, rng, count: int) -> list[np.ndarray]:
        """``count`` cube positions in the task's region, each more than ``APART_M`` from the others.

        Drawn together and redrawn together: checking a new cube against the body position of one
        just placed read MuJoCo's kinematics before they were recomputed (the origin, after
        ``mj_resetData``), so distractors landed anywhere, and a cube placed first in the middle
        of a small region can leave no spot far enough from it.
        """
        x0, x1, y0, y1 = self.task.region
        for _ in range(1000):
            spots = [np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]) for _ in range(count)]
            if all(np.linalg.norm(a - b) > APART_M for i, a in enumerate(spots) for b in spots[i + 1 :]):
                return spots
        raise RuntimeError(f"No {count} cube positions {APART_M} m apart in the region {self.task.region}.")

    def _grade(self) -> bool:
        """Update the episode's graded outcome; whether the cube is lifted in the jaws right now.

        The grades are a funnel: each implies the one before it. A grasp reaches the cube even when
        the grasp point is off its centre (both pads on the cube's upper half, say), and a lift
        (success's condition) is a grasp."""
        cube = self.cube_pos()
        held = self._pads_touching()
        if held or np.linalg.norm(self.data.site("grasp").xpos - cube) < REACHED_M:
            self.outcome["reached"] = True
        self.outcome["grasped"] |= held
        lifted = held and cube[2] - CUBE_HALF > LIFTED_M
        self.outcome["lifted"] |= lifted
        return lifted

    def _pads_touching(self) -> bool:
        """Both jaw pads in contact with the cube (over the contact arrays at once: a Python loop
        over the contacts was a tenth of a closed-loop episode's time)."""
        contacts = self.data.contact
        pairs = np.stack([contacts.geom1, contacts.geom2], axis=1)
        with_cube = pairs[(pairs == self._cube_geom).any(axis=1)]
        return bool(np.isin(self._pad_geoms, with_cube).all())

    def _images(self) -> dict[str, np.ndarray]:
        if self.renderer is None:
            self.renderer = open_renderer(self.model, self.height, self.width)
        images = {}
        for camera in ("front", "wrist"):
            self.renderer.update_scene(self.data, camera)
            images[camera] = self.renderer.render().copy()
        return images

    def _info(self, success: bool = False) -> dict:
        return {"is_success": success, **self.outcome}


def make_env(conditions: str = "sim-so101-eval", height: int = 128, width: int = 128) -> PickCubeEnv:
    """The env in one recorded set-up's conditions (``zk0.sim.tasks.SIM_SPECS``), by name: what
    ``gym.make`` builds for lerobot's ``zk0_so101`` env config."""
    return PickCubeEnv(SIM_SPECS[conditions].task, height, width)
