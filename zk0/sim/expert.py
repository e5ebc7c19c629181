"""The scripted expert that demonstrates each task: Cartesian waypoints, damped-least-squares IK.

It reads the cubes' and pads' poses from the simulator (a policy never can), plans a top-down grasp
(above the cube, down, close, lift) and, for a task that moves the cube somewhere, the carry (over
its pad or the lower cube, down, open, back up; a sort does it for each cube), and at each
control step solves the arm's inverse
kinematics for the next point of that path with ``mj_jacSite`` on a copy of the model's
state. It returns joint targets in lerobot units, as a leader arm would command them, so its
episodes record exactly like teleoperated SO-101 data. ``speed`` is how fast it moves (m/s):
robot owners' demonstrations differ in pace.
"""

from __future__ import annotations

import numpy as np

from zk0.sim import load_mujoco
from zk0.sim.env import PickCubeEnv, to_lerobot

mujoco = load_mujoco()
ARM = 4  # shoulder_pan .. wrist_flex solve position and pointing; wrist_roll turns the jaws to the cube
OPEN, CLOSED = 55.0, 0.0  # gripper targets (lerobot 0-100)
ABOVE_M, LIFT_M = 0.07, 0.05  # approach height over the cube, and how high a pick-up lifts it
DROP_M = 0.004  # a carried cube is let go this far above where it rests


def skew(v: np.ndarray) -> np.ndarray:
    """The matrix of ``v x .``."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def smoothstep(s: float) -> float:
    s = min(1.0, max(0.0, s))
    return s * s * (3 - 2 * s)


class PickExpert:
    """One episode's plan, made at ``reset`` from the env's state; ``act`` gives the next action."""

    def __init__(self, env: PickCubeEnv, speed: float = 0.15):
        self.env, self.speed = env, speed
        self.model = env.model
        self.ik = mujoco.MjData(self.model)  # IK works on its own copy: the simulation is not touched
        self.site = self.model.site("grasp").id
        self.dt = 1.0 / env.task.fps

    def reset(self) -> None:
        """Plan the path from where the grasp point is now: to the cube and up, and for a task
        that moves cubes, on to where each goes."""
        env = self.env
        self.q = env.data.qpos[env.joint_ids].copy()  # the targets the expert last commanded (rad)
        start = env.data.site("grasp").xpos.copy()
        rolls = {name: self._roll_for(env.cube_yaw(name), env.cube_pos(name) + [0, 0, ABOVE_M]) for name in env.movers}
        # (where to, gripper, seconds, wrist roll): seconds from distance and speed, with floors for the slow parts
        self.plan, at = [], start
        for name in env.movers:
            at = self._grasp(env.cube_pos(name), rolls[name], at)
            if env.task.kind != "pick":
                at = self._carry(env.target_of(name), rolls[name], at)
        self.plan.append((at, self.plan[-1][1], 10.0, self.plan[-1][3]))  # then stay there
        self.leg, self.t, self.origin = 0, 0.0, start
        self.gripper_from = float(env.joint_pos()[5])
        self.roll = self.roll_from = self.plan[0][3]

    def _grasp(self, cube: np.ndarray, roll: float, start: np.ndarray) -> np.ndarray:
        """Legs that take the cube at ``cube`` from ``start``: over it, down, close, up (a pick-up's
        lift; a carry's travelling height). Returns where they end."""
        above = cube + [0, 0, ABOVE_M]
        height = LIFT_M if self.env.task.kind == "pick" else ABOVE_M
        up = cube + [0, 0, height]
        self.plan += [
            (above, OPEN, max(0.6, np.linalg.norm(above - start) / self.speed), roll),
            (cube, OPEN, max(0.5, ABOVE_M / (0.5 * self.speed)), roll),
            (cube, CLOSED, 0.6, roll),
            (up, CLOSED, max(0.5, height / (0.5 * self.speed)), roll),
        ]
        return up

    def _carry(self, rest: np.ndarray, roll: float, start: np.ndarray) -> np.ndarray:
        """Legs that bring a held cube from ``start`` to rest with its centre at ``rest``: over it,
        down, open, back up. Returns where they end."""
        above, release = rest + [0, 0, ABOVE_M], rest + [0, 0, DROP_M]
        lower = max(0.5, ABOVE_M / (0.5 * self.speed))
        self.plan += [
            (above, CLOSED, max(0.6, np.linalg.norm(above - start) / self.speed), roll),
            (release, CLOSED, lower, roll),
            (release, OPEN, 0.5, roll),
            (above, OPEN, lower, roll),
        ]
        return above

    def act(self) -> np.ndarray:
        """The next joint targets (lerobot units)."""
        goal, gripper, duration, roll = self.plan[self.leg]
        self.t += self.dt
        s = smoothstep(self.t / duration)
        point = self.origin + s * (goal - self.origin)
        grip = self.gripper_from + s * (gripper - self.gripper_from)
        self.roll = self.roll_from + s * (roll - self.roll_from)
        if self.t >= duration and self.leg + 1 < len(self.plan):
            self.leg, self.t, self.origin, self.gripper_from, self.roll_from = self.leg + 1, 0.0, goal, gripper, roll
        self.q[:ARM] = self._solve(point)
        self.q[ARM] = self.roll
        action = to_lerobot(self.q, self.env.gripper_range)
        action[5] = grip
        return action

    def _roll_for(self, yaw: float, above: np.ndarray) -> float:
        """wrist_roll that turns the jaws square to the cube's faces (a cube repeats every 90°),
        found with the arm posed over the cube: turning the roll turns the jaws by as much."""
        low, high = self.model.jnt_range[self.model.joint("wrist_roll").id]
        self.roll = 0.0
        for _ in range(3):
            q = self.q.copy()
            q[:ARM], q[ARM] = self._solve(above), self.roll
            self._kinematics(q)
            closing = self.ik.site_xmat[self.site].reshape(3, 3)[:, 0]  # the jaws close along the site's x
            offset = (yaw - np.arctan2(closing[1], closing[0]) + np.pi / 4) % (np.pi / 2) - np.pi / 4
            self.roll = float(np.clip(self.roll + offset, low, high))
        return self.roll

    def _kinematics(self, q: np.ndarray) -> None:
        self.ik.qpos[self.env.joint_ids] = q
        mujoco.mj_kinematics(self.model, self.ik)
        mujoco.mj_comPos(self.model, self.ik)

    def _solve(self, target: np.ndarray, iterations: int = 15, damping: float = 1e-3) -> np.ndarray:
        """Arm joints that put the grasp point at ``target`` with the jaws pointing straight down."""
        q = self.q.copy()
        q[ARM] = self.roll
        jac_pos, jac_rot = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        dofs = [self.model.jnt_dofadr[self.model.joint(n).id] for n in range(ARM)]
        limits = self.model.jnt_range[:ARM]
        for _ in range(iterations):
            self._kinematics(q)
            mujoco.mj_jacSite(self.model, self.ik, jac_pos, jac_rot, self.site)
            axis = -self.ik.site_xmat[self.site].reshape(3, 3)[:, 2]  # the way the fingers point
            error = np.concatenate([target - self.ik.site_xpos[self.site], 0.3 * (np.array([0, 0, -1.0]) - axis)[:2]])
            jac_axis = -skew(axis) @ jac_rot  # d(axis)/dt = omega x axis
            jac = np.vstack([jac_pos[:, dofs], 0.3 * jac_axis[:2, dofs]])
            step = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(len(error)), error)
            q[:ARM] = np.clip(q[:ARM] + step, limits[:, 0], limits[:, 1])
            if np.linalg.norm(error) < 1e-4:
                break
        return q[:ARM]

