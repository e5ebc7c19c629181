"""``PickCubeEnv``: an SO-101 picking up a cube (or placing, stacking or sorting cubes: the set-up's
``kind``), in lerobot's SO-101 units, as a gymnasium env.

State and action are the six ``*.pos`` values a real SO-101 dataset records (lerobot's
``so101_follower`` with degrees): the five arm joints in degrees, zero at the middle of each
joint's range as in the MJCF's "new calibration", and the gripper from 0 (closed) to 100 (open).
The action is the joint targets the servos move to, as a leader arm commands them. The
observation is lerobot's env contract: ``pixels`` (``front`` and ``wrist`` cameras, uint8 HxWx3)
and ``agent_pos``; ``task_description`` is the instruction (which cube, and where it goes). Every
step's ``info`` carries ``is_success`` (lerobot 0.6.1's ``rollout`` counts a missing key as a
success) and the episode's graded outcome so far: reached, grasped, lifted, and for a task that
moves a cube somewhere, placed. In a task with ``cube_in_state`` (a privileged study setting) the
state also carries, in centimetres on the table, the xy of the cube to move and of where it goes
(``privileged_names``): a pick-up's state is eight values instead of six.
"""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np

from zk0.sim import cannot_render, load_mujoco
from zk0.sim.scene import CUBE_HALF, JAW_PADS, PAD_HALF, PADS, build_spec
from zk0.sim.tasks import INSTRUCTIONS, SIM_SPECS, SimTask

mujoco = load_mujoco()

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
# What a cube_in_state task's state carries after the joints (xy in cm): the cube to move and where
# it goes (the named pad, the cube to stack on; a sort's second cube and its pad after the first).
PRIVILEGED = {
    "pick": ("cube",),
    "place": ("cube", "pad"),
    "stack": ("cube", "distractor"),
    "sort": ("cube", "pad", "distractor", "pad2"),
}
# The one layout every kind's state shares in a multi-task set-up (``SimTask.shared_state``): the
# cube to move, where it goes, a sort's second cube and where that goes (None: zero, as a kind has none).
SHARED = {
    "pick": ("cube", None, None, None),
    "place": ("cube", "pad", None, None),
    "stack": ("cube", "distractor", None, None),
    "sort": ("cube", "pad", "distractor", "pad2"),
}
SHARED_NAMES = ("cube", "goal", "cube2", "goal2")
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
APART_M = 0.06  # the cubes' (and pads') centres at least this far apart at every reset
ON_PAD_M = PAD_HALF - 0.005  # a cube whose centre lies this close to its pad's centre (each axis) is on it
ON_CUBE_M = 0.012  # ... this close to the lower cube's centre (xy) is stacked on it
RESTING_M = 0.005  # ... and its centre this close to the height it rests at


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


def privileged_names(task: SimTask) -> tuple[str, ...]:
    """The names of what a ``cube_in_state`` task's state holds after the joints (none otherwise):
    a pick-up's ``cube.x``, ``cube.y``, as its recorded datasets name them; in a multi-task set-up
    every kind's eight (``SHARED``)."""
    if not task.cube_in_state:
        return ()
    if task.shared_state:
        return tuple(f"{body}.{axis}" for body in SHARED_NAMES for axis in "xy")
    names = {"cube": "cube", "pad": "pad", "distractor": "cube2", "pad2": "pad2"}
    return tuple(f"{names[body]}.{axis}" for body in PRIVILEGED[task.kind] for axis in "xy")


def state_size(task: SimTask) -> int:
    """How many values the task's state holds: the six joints, and what it is told of the cubes."""
    return len(JOINTS) + len(privileged_names(task))


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
    """Pick up the named cube, or move cubes where the instruction says (``task.kind``). One model,
    built once; renderers closed by ``close()``."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, task: SimTask | None = None, height: int = 128, width: int = 128, render_mode="rgb_array"):
        self.task = task or SimTask()
        self.height, self.width, self.render_mode = height, width, render_mode
        self.metadata = {**self.metadata, "render_fps": self.task.fps}
        kind = self.task.kind
        self.two_cubes = self.task.distractor or kind in ("stack", "sort")
        self.model = build_spec(self.task.look, self.two_cubes, pads=2 if kind in ("place", "sort") else 0).compile()
        self.data = mujoco.MjData(self.model)
        self.joint_ids = [self.model.joint(name).qposadr[0] for name in JOINTS]
        self._cube_geom = self.model.geom("cube").id
        # The cubes this task moves: the named one, and a sort's second cube.
        self.movers = ("cube", "distractor") if kind == "sort" else ("cube",)
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
        self.names = {"cube": self.colour}  # the colour each instruction slot names, drawn at every reset
        self.template = INSTRUCTIONS[kind][0]
        self.outcome = self._fresh_outcome()
        self.steps = self._held = 0

    @property
    def task_description(self) -> str:
        """The instruction: which cube, and where it goes."""
        return self.template.format(**self.names)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        rng = self.np_random
        colours = list(self.task.colours)
        self.colour = colours.pop(int(rng.integers(len(colours))))
        self.names = {"cube": self.colour}
        spots = self._spots(rng, 2 if self.two_cubes else 1)
        self._place("cube", spots[0], self.colour, rng)
        if self.two_cubes:
            other = colours[int(rng.integers(len(colours)))] if colours else "green"
            self._place("distractor", spots[1], other, rng)
            self.names["base"] = other  # a stack's lower cube
        if self.task.kind != "pick":
            self._arrange(rng, spots)
        home = HOME + rng.normal(0.0, 2.0, size=6) * np.array([1, 1, 1, 1, 1, 0])
        self.data.qpos[self.joint_ids] = to_mujoco(home, self.gripper_range)
        self.data.ctrl[:] = self.data.qpos[self.joint_ids]
        mujoco.mj_step(self.model, self.data, nstep=50)  # let the cubes settle on the table
        self.outcome = self._fresh_outcome()
        self.steps = self._held = 0
        return self.observe(), self._info()

    def step(self, action):
        reward, success = self.act(action)
        return self.observe(), reward, success, False, self._info(success)

    def act(self, action) -> tuple[float, bool]:
        """``step`` without the observation: the servos move to ``action`` for one control period.
        Returns the graded reward so far (0-3, or 0-4 with placed) and whether the task is now done
        for long enough (success, which ends the episode): the cube held up, or every cube resting
        where it goes, released. zk0.learning.closed_loop renders only the steps a
        chunking policy reads, so it calls this and ``observe`` apart."""
        target = np.clip(np.asarray(action, dtype=np.float64), self.action_space.low, self.action_space.high)
        self.data.ctrl[:] = to_mujoco(target, self.gripper_range)
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        self.steps += 1
        done = self._grade()
        self._held = self._held + 1 if done else 0
        return float(sum(self.outcome.values())), self._held >= HOLD_STEPS

    def observe(self) -> dict:
        """The observation now: both cameras rendered, and the state."""
        state = self.joint_pos()
        if self.task.cube_in_state:
            bodies = SHARED[self.task.kind] if self.task.shared_state else PRIVILEGED[self.task.kind]
            places = [self.place_of(body)[:2] if body else np.zeros(2) for body in bodies]
            state = np.concatenate([state, 100.0 * np.concatenate(places)]).astype(np.float32)
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

    def place_of(self, name: str) -> np.ndarray:
        """Where a cube's centre, or a pad's, is now."""
        return self.data.geom(name).xpos.copy() if name in PADS else self.cube_pos(name)

    def target_of(self, cube: str) -> np.ndarray:
        """Where ``cube``'s centre rests once it is where its task puts it: on its pad, or on the
        lower cube (a pick-up's cube has no such place)."""
        if self.task.kind == "stack":
            return self.cube_pos("distractor") + [0.0, 0.0, 2 * CUBE_HALF]
        pad = "pad" if cube == "cube" else "pad2"
        return np.array([*self.place_of(pad)[:2], CUBE_HALF])

    def rests_on_target(self, cube: str) -> bool:
        """``cube`` rests where its task puts it now: its centre over the pad (or on the lower cube's
        centre) and at the height it rests at there."""
        offset = self.cube_pos(cube) - self.target_of(cube)
        if self.task.kind == "stack":
            over = np.linalg.norm(offset[:2]) < ON_CUBE_M
        else:
            over = np.abs(offset[:2]).max() < ON_PAD_M
        return bool(over and abs(offset[2]) < RESTING_M)

    def holds(self, cube: str = "cube") -> bool:
        """Both jaw pads in contact with ``cube`` (over the contact arrays at once: a Python loop
        over the contacts was a tenth of a closed-loop episode's time)."""
        contacts = self.data.contact
        pairs = np.stack([contacts.geom1, contacts.geom2], axis=1)
        geom = self._cube_geom if cube == "cube" else self.model.geom(cube).id
        with_cube = pairs[(pairs == geom).any(axis=1)]
        return bool(np.isin(self._pad_geoms, with_cube).all())

    def cube_yaw(self, name: str = "cube") -> float:
        w, x, y, z = self.data.body(name).xquat
        return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))

    def joint_pos(self) -> np.ndarray:
        """The joints now, in lerobot units."""
        return to_lerobot(self.data.qpos[self.joint_ids], self.gripper_range)

    def _place(self, name: str, xy: np.ndarray, colour: str, rng) -> None:
        joint = self.model.joint(name)
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        self.data.qpos[joint.qposadr[0] : joint.qposadr[0] + 7] = [*xy, CUBE_HALF, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self.model.geom_rgba[self.model.geom(name).id] = COLOURS[colour]

    def _arrange(self, rng, cubes: list[np.ndarray]) -> None:
        """What a task that moves cubes adds to a pick-up's reset: its pads, placed apart from the
        cubes and coloured, and its instruction's wording (drawn after the pick-up's draws)."""
        if self.task.kind in ("place", "sort"):
            spots = self._spots(rng, 2, self.task.pad_region, avoid=cubes, what="pad")
            if self.task.kind == "sort":  # each cube's pad has its colour
                colours = [self.names["cube"], self.names["base"]]
            else:  # the named pad, and another of another colour
                colours = [str(c) for c in rng.choice(list(COLOURS), size=2, replace=False)]
                self.names["pad"] = colours[0]
            for pad, spot, colour in zip(PADS, spots, colours, strict=True):
                geom = self.model.geom(pad).id
                self.model.geom_pos[geom][:2] = spot
                self.model.geom_rgba[geom] = COLOURS[colour]
        templates = INSTRUCTIONS[self.task.kind]
        self.template = templates[int(rng.integers(len(templates)))]

    def _spots(
        self, rng, count: int, region: tuple | None = None, avoid: list[np.ndarray] = (), what: str = "cube"
    ) -> list[np.ndarray]:
        """``count`` positions in ``region`` (the task's, for cubes), each more than ``APART_M``
        from the others and from those in ``avoid``.

        Drawn together and redrawn together: checking a new cube against the body position of one
        just placed read MuJoCo's kinematics before they were recomputed (the origin, after
        ``mj_resetData``), so distractors landed anywhere, and a cube placed first in the middle
        of a small region can leave no spot far enough from it.
        """
        region = region or self.task.region
        x0, x1, y0, y1 = region
        for _ in range(1000):
            spots = [np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]) for _ in range(count)]
            every = [*avoid, *spots]
            if all(np.linalg.norm(a - b) > APART_M for i, a in enumerate(every) for b in every[i + 1 :]):
                return spots
        raise RuntimeError(f"No {count} {what} positions {APART_M} m apart in the region {region}.")

    def _fresh_outcome(self) -> dict[str, bool]:
        """The funnel's grades, none met yet: a task that moves cubes somewhere adds placed."""
        grades = ("reached", "grasped", "lifted") + (("placed",) if self.task.kind != "pick" else ())
        return dict.fromkeys(grades, False)

    def _grade(self) -> bool:
        """Update the episode's graded outcome; whether the task's end holds right now (a pick-up's
        cube lifted in the jaws; every moved cube resting where it goes, released).

        The grades are a funnel: each implies the one before it. A grasp reaches the cube even when
        the grasp point is off its centre (both pads on the cube's upper half, say), a lift is a
        grasp, and a cube is placed only once it was lifted there. For a sort, each grade is met
        by either cube, and placed by one."""
        done = True
        for name in self.movers:
            cube = self.cube_pos(name)
            held = self.holds(name)
            if held or np.linalg.norm(self.data.site("grasp").xpos - cube) < REACHED_M:
                self.outcome["reached"] = True
            self.outcome["grasped"] |= held
            lifted = held and bool(cube[2] - CUBE_HALF > LIFTED_M)
            self.outcome["lifted"] |= lifted
            if self.task.kind == "pick":
                return lifted
            placed = self.outcome["lifted"] and not held and self.rests_on_target(name)
            self.outcome["placed"] |= placed
            done &= placed
        return done

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


def make_env(
    conditions: str = "sim-so101-eval", height: int = 128, width: int = 128, kind: str | None = None
) -> PickCubeEnv:
    """The env in one recorded set-up's conditions (``zk0.sim.tasks.SIM_SPECS``), by name, doing its
    own task (a multi-task set-up's first) or the ``kind`` given: what ``gym.make`` builds for
    lerobot's ``zk0_so101`` env config."""
    task = SIM_SPECS[conditions].task
    return PickCubeEnv(replace(task, kind=kind) if kind else task, height, width)
