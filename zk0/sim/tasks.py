"""What each simulated robot owner's set-up looks like, what it teaches, and the demonstration
datasets recorded in it.

Plain data, no MuJoCo: the registry and ``zk0 assets`` read it to know which datasets zk0
records. The four clients differ the way robot owners do: each puts its cubes in its own part
of the table, with its own cube colours, lighting, front-camera placement and demonstration
pace; the server's evaluation set spans all of them (every region, colour and camera), so a
policy is judged on conditions each client never saw. Each set-up also has a ``-cube`` twin whose
state carries the target cube's position (``SimTask.cube_in_state``), for the privileged study.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from zk0.common.catalogue import Catalogue

# Bumped whenever the scene, env or expert changes what is recorded: cached datasets are recorded again.
RECORDER_VERSION = 3
CAMERAS = ("front", "wrist")  # every recording's cameras (zk0.sim.record)
SPAN = (0.16, 0.28, -0.12, 0.12)  # x0, x1, y0, y1 (m): the part of the table the server's set-up spans
# What an owner teaches: pick up the named cube; put it on the pad of a named colour; stack it on
# another named cube; or sort two cubes, each onto the pad of its own colour.
KINDS = ("pick", "place", "stack", "sort")
# How long an episode of each kind may run (s): room for the expert at its slowest pace, 0.12 m/s
# (a pick-up ~4 s, a place or stack up to 8 s, a sort, two carries, up to 16 s).
EPISODE_S = {"pick": 10.0, "place": 10.0, "stack": 10.0, "sort": 20.0}
# How each kind may be asked for (zk0.sim.env fills in the colours; one is drawn per episode). Pick-up
# keeps its one sentence: its recorded datasets, and every figure measured on them, stay as they were.
INSTRUCTIONS = {
    "pick": ("Pick up the {cube} cube",),
    "place": ("Put the {cube} cube on the {pad} pad", "Place the {cube} cube onto the {pad} pad"),
    "stack": ("Stack the {cube} cube on the {base} cube", "Put the {cube} cube on top of the {base} cube"),
    "sort": ("Put each cube on the pad of its colour", "Sort the cubes onto the pads of their colours"),
}


@dataclass(frozen=True)
class Look:
    """What differs between robot owners' rooms: lighting, front-camera placement, table colour."""

    light: float = 0.7  # diffuse intensity of the main light
    light_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    front_camera: tuple[float, float, float] = (0.55, 0.0, 0.45)  # where the front camera stands (m)
    table_rgba: tuple[float, float, float, float] = (0.55, 0.45, 0.35, 1.0)


@dataclass(frozen=True)
class SimTask:
    """One set-up: what it teaches, where cubes appear, their colours, the look, how long an episode may run."""

    region: tuple[float, float, float, float] = SPAN  # x0, x1, y0, y1 (m) of the cube
    colours: tuple[str, ...] = ("red", "blue")
    distractor: bool = True  # a second cube of another colour: the task text says which one to pick
    look: Look = field(default_factory=Look)
    fps: int = 30
    episode_s: float | None = None  # how long an episode may run; None: its kind's (EPISODE_S)
    # The target cube's xy on the table appended to the joint state: privileged, as ManiSkill's
    # "state" observations are. A study setting only (a real robot's policy is not told where the
    # cube is): it separates "cannot locate the cube in the frames" from "cannot act on where it is".
    # A task that moves the cube somewhere carries that place too (zk0.sim.env.privileged_names).
    cube_in_state: bool = False
    kind: str = "pick"  # one of KINDS
    # Where the coloured pads of a place or sort task lie (x0, x1, y0, y1, m): the server's span, as
    # an owner's region alone is too small for two cubes and two pads 6 cm apart.
    pad_region: tuple[float, float, float, float] = SPAN
    # With cube_in_state: the state in the one layout every kind shares (the cube, where it goes, a
    # sort's second cube and where that goes; zero where a kind has none), so owners who teach
    # different tasks federate one policy (a multi-task set-up, ``with_kinds``).
    shared_state: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"A simulated task's kind is {self.kind!r}; expected one of {', '.join(KINDS)}.")
        if self.kind in ("stack", "sort") and len(self.colours) < 2:
            raise ValueError(
                f"A {self.kind} task names two cubes; its colours are {self.colours}, expected two or more."
            )

    @property
    def max_steps(self) -> int:
        return round(self.fps * (self.episode_s or EPISODE_S[self.kind]))


@dataclass(frozen=True)
class DemoSpec:
    """A demonstration dataset: the set-up it is recorded in and how the expert moves."""

    name: str
    repo_id: str
    task: SimTask
    speed: float = 0.15  # the expert's pace (m/s)
    episodes: int = 4  # `zk0 assets`' default: the quick preset's and the tests'; the study records 30-100
    height: int = 128
    width: int = 128
    role: str = "client"
    cameras: tuple[str, ...] = CAMERAS
    kinds: tuple[str, ...] = ()  # what its episodes teach, in turn (``with_kinds``); empty: the task's kind

    @property
    def tasks(self) -> tuple[SimTask, ...]:
        """The task of each kind it teaches, in the order its episodes take them."""
        return tuple(replace(self.task, kind=kind) for kind in self.kinds) if self.kinds else (self.task,)


def with_cube_in_state(spec: DemoSpec) -> DemoSpec:
    """The same set-up and expert, recorded with the cube's position in the state (``-cube``)."""
    return replace(
        spec, name=f"{spec.name}-cube", repo_id=f"{spec.repo_id}_cube", task=replace(spec.task, cube_in_state=True)
    )


def with_kinds(spec: DemoSpec, kinds: tuple[str, ...]) -> DemoSpec:
    """The same set-up teaching ``kinds``, its episodes taking them in turn (``sim-so101-left-place``,
    ``sim-so101-eval-pick-place-stack-sort``), its state in the layout every kind shares."""
    if len(set(kinds)) != len(kinds) or not set(kinds) <= set(KINDS):
        raise KeyError(f"{spec.name}-{'-'.join(kinds)}")
    suffix = "-".join(kinds)
    return replace(
        spec,
        name=f"{spec.name}-{suffix}",
        repo_id=f"{spec.repo_id}_{suffix.replace('-', '_')}",
        task=replace(spec.task, kind=kinds[0], shared_state=True),
        kinds=kinds,
    )


SERVER_TASK = SimTask(region=SPAN, colours=("red", "blue", "green", "yellow"))
OWNERS: tuple[DemoSpec, ...] = (
    DemoSpec(
        "sim-so101-left",
        "zk0/sim_so101_left",
        SimTask(region=(0.16, 0.22, 0.0, 0.12), colours=("red", "blue"), look=Look(light=0.8)),
        speed=0.12,
    ),
    DemoSpec(
        "sim-so101-right",
        "zk0/sim_so101_right",
        SimTask(
            region=(0.16, 0.22, -0.12, 0.0),
            colours=("green", "yellow"),
            look=Look(light=0.55, light_tint=(1.0, 0.9, 0.75), front_camera=(0.55, -0.08, 0.42)),
        ),
        speed=0.18,
    ),
    DemoSpec(
        "sim-so101-far-left",
        "zk0/sim_so101_far_left",
        SimTask(
            region=(0.22, 0.28, 0.0, 0.12),
            colours=("red", "green"),
            look=Look(light=0.9, light_tint=(0.85, 0.9, 1.0), front_camera=(0.53, 0.07, 0.47)),
        ),
        speed=0.15,
    ),
    DemoSpec(
        "sim-so101-far-right",
        "zk0/sim_so101_far_right",
        SimTask(
            region=(0.22, 0.28, -0.12, 0.0),
            colours=("blue", "yellow"),
            look=Look(light=0.65, front_camera=(0.57, 0.0, 0.43), table_rgba=(0.5, 0.5, 0.5, 1.0)),
        ),
        speed=0.2,
    ),
    DemoSpec("sim-so101-eval", "zk0/sim_so101_eval", SERVER_TASK, episodes=6, role="server"),
)
OWNER_SEED = 2026  # owner N's set-up comes from numpy's generator seeded with (OWNER_SEED, N)
TASK_SEED = 2029  # ... and what it teaches in a multi-task federation from (TASK_SEED, N)
TWO_TASKS = 0.25  # the share of generated owners who teach two tasks
PUBLIC_SEED = 2028  # public set-up N's from (PUBLIC_SEED, N) (2027 is OUTSIDE_SEED)
# What generated owners' rooms are drawn from: together with the hand-written owners', the span of
# conditions a federation trains in (conditions outside it are drawn beyond every bound).
OWNER_LIGHT = (0.55, 0.9)  # the main light's diffuse intensity
OWNER_TINT = (0.85, 1.0)  # each channel of the light's tint
OWNER_CAMERA = ((0.53, 0.57), (-0.08, 0.08), (0.42, 0.47))  # the front camera's x, y, z (m)
OWNER_TABLE = (0.45, 0.6)  # each channel of the table's colour


def sim_owner(index: int) -> DemoSpec:
    """Owner ``index`` of a many-owner federation (``sim-so101-owner-<index>``): a 6 x 12 cm part of
    the server's span, two of its four cube colours, its own lighting, front camera and table, and
    the expert's pace, drawn from a seeded distribution spanning the four hand-written owners'."""
    return drawn_setup(OWNER_SEED, index, f"sim-so101-owner-{index}", f"zk0/sim_so101_owner_{index}")


def sim_public(index: int) -> DemoSpec:
    """Public set-up ``index`` (``sim-so101-public-<index>``): demonstrations the server records in
    rooms of its own, to pretrain on before any owner federates (the public starting point a real
    federation has, as smolvla_base's community datasets). Drawn from the owners' distribution
    with a seed of its own, so no public set-up is an owner's or an evaluation condition."""
    return drawn_setup(PUBLIC_SEED, index, f"sim-so101-public-{index}", f"zk0/sim_so101_public_{index}")


def drawn_kinds(index: int) -> tuple[str, ...]:
    """What generated owner ``index`` teaches in a multi-task federation (``sim-so101-owner-<N>-task``):
    one kind, or two for a quarter of owners, drawn with a seed of its own, so its room is
    ``sim-so101-owner-<N>``'s."""
    rng = np.random.default_rng([TASK_SEED, index])
    count = 2 if rng.random() < TWO_TASKS else 1
    drawn = sorted(rng.choice(len(KINDS), size=count, replace=False))  # named in KINDS' order
    return tuple(KINDS[int(k)] for k in drawn)


def drawn_setup(seed: int, index: int, name: str, repo_id: str) -> DemoSpec:
    """Set-up ``index`` of the draws seeded with ``seed``: region, colours, room and pace."""
    rng = np.random.default_rng([seed, index])
    x0, y0 = float(rng.uniform(0.16, 0.22)), float(rng.uniform(-0.12, 0.0))
    colours = rng.choice(len(SERVER_TASK.colours), size=2, replace=False)
    look = Look(
        light=float(rng.uniform(*OWNER_LIGHT)),
        light_tint=tuple(float(c) for c in rng.uniform(*OWNER_TINT, size=3)),
        front_camera=tuple(float(rng.uniform(*axis)) for axis in OWNER_CAMERA),
        table_rgba=(*(float(c) for c in rng.uniform(*OWNER_TABLE, size=3)), 1.0),
    )
    task = SimTask(
        region=(x0, x0 + 0.06, y0, y0 + 0.12),
        colours=tuple(SERVER_TASK.colours[int(c)] for c in sorted(colours)),
        look=look,
    )
    return DemoSpec(name, repo_id, task, speed=float(rng.uniform(0.12, 0.2)))


OUTSIDE_SEED = 2027
OUTSIDE = ("dim", "bright", "tint", "camera", "table")  # the look's axes a condition outside the span varies


def outside_condition(axis: str, index: int, base: DemoSpec | None = None) -> DemoSpec:
    """Condition ``index`` outside the span on one ``axis``: the server's task and look
    (``sim-so101-outside-<axis>-<index>``), or a hand-written owner's (``base``:
    ``sim-so101-left-outside-<axis>-<index>``), with that one axis drawn beyond every owner's, so a
    benchmark measures how a model generalises, not how it was tuned. A pure function of its name,
    like the owners; the same axis and index draw the same value whatever the base."""
    rng = np.random.default_rng([OUTSIDE_SEED, OUTSIDE.index(axis), index])
    task = base.task if base else SERVER_TASK
    look = task.look
    if axis == "dim":
        look = replace(look, light=float(rng.uniform(0.2, 0.45)))
    elif axis == "bright":
        look = replace(look, light=float(rng.uniform(1.0, 1.3)))
    elif axis == "tint":  # one channel far below any owner's (the lowest is the right owner's blue, 0.75)
        tint = [1.0, 1.0, 1.0]
        tint[int(rng.integers(3))] = float(rng.uniform(0.35, 0.65))
        look = replace(look, light_tint=tuple(tint))
    elif axis == "camera":  # moved sideways past the owners' spread, and higher or lower than any
        x, _, _ = look.front_camera
        side = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(0.11, 0.16))
        height = float(rng.choice([rng.uniform(0.36, 0.40), rng.uniform(0.49, 0.52)]))
        look = replace(look, front_camera=(x, side, height))
    else:  # a table darker or lighter than any owner's, in every channel
        low = bool(rng.integers(2))
        colour = rng.uniform(0.1, 0.25, size=3) if low else rng.uniform(0.72, 0.9, size=3)
        look = replace(look, table_rgba=(*(float(c) for c in colour), 1.0))
    prefix = base.name if base else "sim-so101"
    return DemoSpec(
        f"{prefix}-outside-{axis}-{index}",
        f"{prefix.replace('sim-so101', 'zk0/sim_so101').replace('-', '_')}_outside_{axis}_{index}",
        replace(task, look=look),
        episodes=6,
        role="server",
    )


# How far beyond the other owners' span a look must lie before a report says so (light, tint and
# table channels; the front camera's place in metres): the outside conditions lie further still.
SPAN_MARGIN = 0.05
CAMERA_MARGIN = 0.02


def beyond_span(look: Look, others: list[Look]) -> list[str]:
    """How ``look`` lies beyond the span of ``others`` (each phrase one axis; none: inside it), so
    report.html can tell an owner that the federation met its room only in its own frames."""
    phrases = []
    lights = [o.light for o in others]
    lit = f"({look.light:.2f}) than any other owner's room ({min(lights):.2f}-{max(lights):.2f})"
    if look.light < min(lights) - SPAN_MARGIN:
        phrases.append(f"lit more dimly {lit}")
    if look.light > max(lights) + SPAN_MARGIN:
        phrases.append(f"lit more brightly {lit}")
    for channel, name in enumerate(("red", "green", "blue")):
        lowest = min(o.light_tint[channel] for o in others)
        if look.light_tint[channel] < lowest - SPAN_MARGIN:
            phrases.append(
                f"its light has less {name} ({look.light_tint[channel]:.2f}) than any other's ({lowest:.2f})"
            )
    for axis, name in ((1, "sideways"), (2, "in height")):
        values = [o.front_camera[axis] for o in others]
        if not min(values) - CAMERA_MARGIN <= look.front_camera[axis] <= max(values) + CAMERA_MARGIN:
            phrases.append(
                f"its front camera stands {name} at {look.front_camera[axis]:.2f} m, beyond every other's "
                f"({min(values):.2f}-{max(values):.2f} m)"
            )
    tables = [c for o in others for c in o.table_rgba[:3]]
    if max(look.table_rgba[:3]) < min(tables) - SPAN_MARGIN or min(look.table_rgba[:3]) > max(tables) + SPAN_MARGIN:
        shade = "darker" if max(look.table_rgba[:3]) < min(tables) else "lighter"
        phrases.append(f"its table is {shade} than any other's")
    return phrases


def _generated(match) -> DemoSpec:
    kind, index = match["kind"], int(match["index"])
    if kind in ("owner", "public"):
        if match["at"]:  # an owner's conditions are made from the server's or a hand-written owner's
            raise KeyError(match.string)
        spec = sim_owner(index) if kind == "owner" else sim_public(index)
    else:
        base = next(o for o in OWNERS if o.name == f"sim-so101-{match['at']}") if match["at"] else None
        spec = outside_condition(kind.removeprefix("outside-"), index, base)
    return with_cube_in_state(spec) if match["cube"] else spec


def _multi_task(match) -> DemoSpec:
    """A multi-task set-up: a hand-written owner's room, the server's, or generated owner N's,
    teaching the kinds its name lists (or, ``-task``, those owner N draws)."""
    owner = match["index"]
    if match["kinds"] == "task":  # drawn: a generated owner's alone
        if owner is None:
            raise KeyError(match.string)
        kinds = drawn_kinds(int(owner))
    else:
        kinds = tuple(match["kinds"].split("-"))
    room = sim_owner(int(owner)) if owner is not None else SIM_SPECS[f"sim-so101-{match['base']}"]
    spec = with_kinds(room, kinds)
    return with_cube_in_state(spec) if match["cube"] else spec


_CLIENTS = "|".join(o.name.removeprefix("sim-so101-") for o in OWNERS if o.role == "client")
_ROOMS = "|".join(o.name.removeprefix("sim-so101-") for o in OWNERS)  # the clients' and the server's
_KIND = f"(?:{'|'.join(KINDS)})"
# sim-so101[-<owner>]-<owner|public|outside-<axis>>-<N>[-cube]: a generated set-up or condition
GENERATED = (
    rf"sim-so101-(?:(?P<at>{_CLIENTS})-)?"
    rf"(?P<kind>owner|public|{'|'.join(f'outside-{axis}' for axis in OUTSIDE)})-(?P<index>\d+)(?P<cube>-cube)?"
)
# sim-so101-<room>-<kind>[-<kind>...][-cube], sim-so101-owner-<N>-task[-cube]: a multi-task set-up
MULTI_TASK = rf"sim-so101-(?P<base>{_ROOMS}|owner-(?P<index>\d+))-(?P<kinds>{_KIND}(?:-{_KIND})*|task)(?P<cube>-cube)?"
SIM_SPECS: Catalogue[DemoSpec] = Catalogue(
    {spec.name: spec for owner in OWNERS for spec in (owner, with_cube_in_state(owner))},
    {GENERATED: _generated, MULTI_TASK: _multi_task},
    "sim-so101-owner-<N>[-cube], sim-so101-public-<N>[-cube], "
    "sim-so101[-<owner>]-outside-<dim|bright|tint|camera|table>-<N>[-cube], "
    "sim-so101-<owner|eval|owner-N>-<pick|place|stack|sort>[-<another kind>...][-cube], sim-so101-owner-<N>-task[-cube]",
)
