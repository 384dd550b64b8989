"""The plan of a simulated fleet, drawn from one seed (pure: no clock, no I/O).

A plan holds the building, and per robot a path of ``L`` poses (:attr:`FleetSpec.poses`), the
robot's odometry at each pose (drifting, or exact) and a noisy scan taken at each pose, all with
the truth to score against. Everything comes from one :class:`numpy.random.Generator` seeded
with :attr:`FleetSpec.seed`, in a fixed order: the building (unless one is given), then robot
after robot its path, its odometry and its ``L`` scans. The same spec gives the same plan, bit
for bit.

A run may be longer than a path: past its last pose a robot drives the path back to its start,
then out again (ping-pong, :meth:`RobotPlan.index`), over and over, its scans those of the way
out. Its odometry goes on drifting: the way back has drift of its own, drawn after every robot's
way out (so that a plan's way out does not depend on it), and each loop starts where the last
one ended (:meth:`RobotPlan.odometry_at`). A run of any length (``rlutf simulate`` until Ctrl-C,
a 30-minute soak) holds one path per robot.

Step 0 is the start: the robot's first odometry and, unless the plan has none, its initial pose.
Its scans and odometry follow at steps 1, 2, ... (step ``k`` at ``k / rate`` seconds).
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from rlutf.map import Map as World
from rlutf.scan import Scan
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)

FloatArray = NDArray[np.float64]
#: What a robot may send besides its odometry and scans: a Relocalize request, or bad input
#: (bytes that are no message at all, or a scan that breaks the schema).
ExtraKind = Literal["relocalize", "malformed", "invalid"]
#: The kinds of bad input, sent in turn.
BAD_KINDS: tuple[ExtraKind, ...] = ("malformed", "invalid")


@dataclass(frozen=True)
class Building:
    """The size of a :func:`rlutf.sim.make_building` floor: metres and rooms."""

    width: float = 24.0
    height: float = 14.0
    rooms_x: int = 3
    rooms_y: int = 2


@dataclass(frozen=True)
class Schedule:
    """Something some robots send now and then (a Relocalize, bad input).

    Attributes:
        every: steps between two sends, at least 1.
        first: the first step it is sent at, at least 1.
        robots: indices of the robots that send it.
    """

    every: int
    first: int = 1
    robots: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        if self.every < 1:
            raise ValueError(
                f"every: a schedule needs at least 1 step between sends, got {self.every}"
            )
        if self.first < 1:
            raise ValueError(
                f"first: step 0 is the start, the first send is at 1 or later, got {self.first}"
            )

    def firing(self, step: int) -> int | None:
        """How many times it was sent before ``step`` when it is due at ``step``, else ``None``."""
        if step < self.first or (step - self.first) % self.every:
            return None
        return (step - self.first) // self.every


@dataclass(frozen=True)
class FleetSpec:
    """What to simulate.

    Attributes:
        robots: how many robots.
        poses: poses of each robot's path, at least 2 (a run past them drives the path back).
        rate_hz: scans (and odometry messages) per second per robot.
        beams: beams per scan (full circle, 12 m, 1 cm noise).
        seed: the seed of the whole plan.
        building: the floor drawn when no map is given to :func:`plan_fleet`.
        map_id: the id the map is put as, and the initial poses name.
        robot_ids: the robots' ids (default ``r000``, ``r001``, ...).
        odometry: the odometry's drift; ``None``: the odometry is the true path.
        initial_poses: the robots announce an InitialPose at the start (else they wait for one).
        initial_offset: added to the true start pose in the InitialPose (m, m, rad).
        relocalize: when robots ask for a global relocalization.
        bad_input: when robots send bad input (kinds :data:`BAD_KINDS` in turn).
    """

    robots: int = 5
    poses: int = 201
    rate_hz: float = 10.0
    beams: int = 360
    seed: int = 0
    building: Building = field(default_factory=Building)
    map_id: str = "sim"
    robot_ids: tuple[str, ...] = ()
    odometry: OdometryModel | None = field(default_factory=OdometryModel)
    initial_poses: bool = True
    initial_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    relocalize: Schedule | None = None
    bad_input: Schedule | None = None

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise ValueError(f"robots: at least 1, got {self.robots}")
        if self.poses < 2:
            raise ValueError(f"poses: a path needs at least 2, got {self.poses}")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz: must be above 0, got {self.rate_hz}")
        if self.beams < 1:
            raise ValueError(f"beams: at least 1, got {self.beams}")
        if self.robot_ids and len(self.robot_ids) != self.robots:
            raise ValueError(f"robot_ids: {len(self.robot_ids)} ids for {self.robots} robots")
        for name in ("relocalize", "bad_input"):
            schedule = getattr(self, name)
            if schedule is not None and not all(0 <= r < self.robots for r in schedule.robots):
                raise ValueError(
                    f"{name}.robots: {schedule.robots} names a robot outside 0..{self.robots - 1}"
                )

    @property
    def ids(self) -> tuple[str, ...]:
        """The robots' ids."""
        return self.robot_ids or tuple(f"r{i:03d}" for i in range(self.robots))

    @property
    def period_ns(self) -> int:
        """Time between two steps, ns."""
        return round(1e9 / self.rate_hz)

    def steps_of(self, seconds: float) -> int:
        """Steps in ``seconds`` at the rate (at least 1)."""
        return max(1, round(seconds * self.rate_hz))


@dataclass(frozen=True, eq=False)
class RobotPlan:
    """One robot's path, odometry and scans.

    Attributes:
        robot_id: its id.
        truth: ``(L, 3)`` true poses along the path (m, m, rad).
        odometry: ``(L, 3)`` what its odometry reads at each pose, in a frame that starts at
            ``truth[0]``.
        scans: the ``L`` scans, one taken at each pose (no return: NaN).
        initial: the pose its InitialPose announces, or ``None`` when it announces none.
        back: ``(L - 1, 3)`` what its odometry reads on the way back, at poses ``L - 2`` down to
            ``0``; ``None``: it retraces the way out's readings.
    """

    robot_id: str
    truth: FloatArray
    odometry: FloatArray
    scans: tuple[Scan, ...]
    initial: FloatArray | None
    back: FloatArray | None = None

    def index(self, step: int) -> int:
        """The pose of the path the robot is at, at ``step`` (out and back, over and over)."""
        n = len(self.truth)
        j = step % (2 * n - 2)
        return j if j < n else 2 * n - 2 - j

    def odometry_at(self, step: int) -> tuple[float, float, float]:
        """What the odometry reads at ``step``: each loop starts where the last one ended."""
        n = 2 * len(self.truth) - 2
        loops, j = divmod(step, n)
        if j < len(self.truth):
            pose = _pose(self.odometry[j])
        else:
            pose = _pose(
                self.odometry[self.index(j)]
                if self.back is None
                else self.back[j - len(self.truth)]
            )
        if loops == 0 or self.back is None:
            return pose
        start = _pose(self.odometry[0])
        loop = _relative(start, _pose(self.back[-1]))
        return _compose(_compose(start, _power(loop, loops)), _relative(start, pose))

    def truth_at(self, step: int) -> FloatArray:
        """The true pose at ``step``."""
        pose: FloatArray = self.truth[self.index(step)]
        return pose


def _pose(p: FloatArray) -> tuple[float, float, float]:
    return (float(p[0]), float(p[1]), float(p[2]))


def _compose(
    a: tuple[float, float, float], b: tuple[float, float, float]
) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (
        a[0] + c * b[0] - s * b[1],
        a[1] + s * b[0] + c * b[1],
        math.remainder(a[2] + b[2], math.tau),
    )


def _relative(
    a: tuple[float, float, float], b: tuple[float, float, float]
) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], math.tau))


def _power(p: tuple[float, float, float], n: int) -> tuple[float, float, float]:
    """``p`` composed with itself ``n`` times (closed form: a rotation's geometric series)."""
    t, turn = complex(p[0], p[1]), cmath.exp(1j * p[2])
    moved = t * n if abs(turn - 1) < 1e-12 else t * (1 - turn**n) / (1 - turn)
    return (moved.real, moved.imag, math.remainder(n * p[2], math.tau))


def plan_robot(
    robot_id: str,
    world: World,
    rng: np.random.Generator,
    poses: int,
    lidar: LidarModel,
    odometry: OdometryModel | None = None,
    dt: float = 0.1,
    initial_offset: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
) -> RobotPlan:
    """One robot: its path, then its odometry, then a scan at each pose, drawn from ``rng``.

    Args:
        robot_id: its id.
        world: the map it drives.
        rng: random generator (advanced by the draws).
        poses: poses of the path, at least 2.
        lidar: its sensor.
        odometry: its odometry's drift (``None``: exact odometry, no draw).
        dt: time between poses, seconds.
        initial_offset: added to its start pose in its InitialPose; ``None``: it announces none.
    """
    truth = make_trajectory(world, rng, poses, dt=dt)
    odom = truth.copy() if odometry is None else drift_odometry(truth, odometry, rng)
    scans = tuple(simulate_scan(world, pose, lidar, rng) for pose in truth)
    initial = None if initial_offset is None else truth[0] + np.asarray(initial_offset)
    return RobotPlan(robot_id, truth, odom, scans, initial)


def with_way_back(
    robot: RobotPlan, odometry: OdometryModel | None, rng: np.random.Generator
) -> RobotPlan:
    """The robot with the drift of its way back drawn (none drawn: ``odometry`` is ``None``)."""
    reverse = robot.truth[::-1]
    read = reverse.copy() if odometry is None else drift_odometry(reverse, odometry, rng)
    end = _pose(robot.odometry[-1])
    back = [_compose(end, _relative(_pose(read[0]), _pose(p))) for p in read[1:]]
    return replace(robot, back=np.asarray(back, dtype=np.float64))


@dataclass(frozen=True, eq=False)
class FleetPlan:
    """A whole fleet: the spec it was drawn from, the map, the robots."""

    spec: FleetSpec
    world: World
    robots: tuple[RobotPlan, ...]

    def extras(self, step: int) -> list[tuple[int, ExtraKind]]:
        """What robots send at ``step`` besides odometry and a scan: (robot index, kind)."""
        out: list[tuple[int, ExtraKind]] = []
        if self.spec.relocalize is not None and self.spec.relocalize.firing(step) is not None:
            out += [(r, "relocalize") for r in self.spec.relocalize.robots]
        bad = self.spec.bad_input
        if bad is not None and (n := bad.firing(step)) is not None:
            out += [(r, BAD_KINDS[n % len(BAD_KINDS)]) for r in bad.robots]
        return out


#: Memory a drawn plan holds per beam of each scan, bytes: its ranges (float64) and their JSON
#: or CDR encoding, with the Python objects around them (about 19 measured, 360 beams).
PLAN_BYTES_PER_BEAM = 20


def plan_bytes(spec: FleetSpec) -> int:
    """About how much memory the plan of ``spec`` and its encoded payloads take, bytes."""
    return spec.robots * spec.poses * spec.beams * PLAN_BYTES_PER_BEAM


def plan_fleet(
    spec: FleetSpec, world: World | None = None, on_robot: Callable[[], None] | None = None
) -> FleetPlan:
    """Draw the plan of ``spec`` (on ``world`` when given, else on a building drawn first);
    ``on_robot`` is called as each robot's path and scans are drawn (a progress bar)."""
    rng = np.random.default_rng(spec.seed)
    if world is None:
        b = spec.building
        world = make_building(
            rng, width=b.width, height=b.height, rooms_x=b.rooms_x, rooms_y=b.rooms_y
        )
    lidar = LidarModel(beams=spec.beams)
    offset = spec.initial_offset if spec.initial_poses else None
    out = []
    for rid in spec.ids:
        dt = 1.0 / spec.rate_hz
        out.append(plan_robot(rid, world, rng, spec.poses, lidar, spec.odometry, dt, offset))
        if on_robot is not None:
            on_robot()
    robots = tuple(with_way_back(robot, spec.odometry, rng) for robot in out)
    return FleetPlan(spec, world, robots)
