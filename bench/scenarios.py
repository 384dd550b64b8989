"""Benchmark scenarios: simulated runs with ground truth, built from named, seeded recipes.

A :class:`Scenario` names a world (a procedural building or a map imported from a ROS grid),
a LiDAR, an odometry model, people and a length; :func:`simulate` turns it and a seed into a
:class:`Run`: the map, the reference poses, the odometry poses and the scans at every scan
stamp. Each part of a run draws from its own generator seeded by ``(seed, part)``, so two
scenarios that differ in one factor (say people) share the building, the path and the
odometry: their results are paired comparisons. Real runs (CARMEN logs) are built as
:class:`Run` too, by :mod:`bench.carmen`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon, box

from rlutf.map import Map
from rlutf.scan import Scan
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    people_walk,
    simulate_scan,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Real data (maps, CARMEN logs) kept in the repository: ``bench/data``, see its README.
DATA = Path(__file__).resolve().parent / "data"
#: Stamp of the first scan of every simulated run, ns since the epoch.
T0_NS = 1_700_000_000_000_000_000
#: Building sizes ``(width, height, rooms_x, rooms_y)`` cycled over the seeds.
BUILDING_SIZES = ((24.0, 14.0, 3, 2), (18.0, 12.0, 2, 2), (30.0, 16.0, 4, 2))


@dataclass(frozen=True)
class Scenario:
    """A recipe for simulated runs.

    Attributes:
        name: short id, used in tables, file names and map ids.
        description: one line for the tables.
        world: ``"building"`` (a procedural building per seed, size cycled over
            :data:`BUILDING_SIZES`), ``"rooms"`` (small rooms off a corridor per seed,
            :func:`make_rooms`) or the stem of a map in ``bench/data/maps``.
        lidar: the sensor.
        odometry: the odometry drift model.
        people: people walking, not on the map.
        steps: scans per run (the first is the start; ``steps - 1`` updates).
        dt: time between scans, seconds.
        speed: forward speed, metres per second.
        clearance: closest approach of the path to a wall, metres.
    """

    name: str
    description: str
    world: str = "building"
    lidar: LidarModel = field(default_factory=LidarModel)
    odometry: OdometryModel = field(default_factory=OdometryModel)
    people: int = 0
    steps: int = 300
    dt: float = 0.1
    speed: float = 0.8
    clearance: float = 0.45


@dataclass(frozen=True, eq=False)
class Run:
    """One run: what a robot would send, and the truth to grade it with.

    Update ``k`` (``1 <= k < len(stamps_ns)``) is: motion ``relative(odometry[k - 1],
    odometry[k])``, scan ``scans[k]``, graded against ``truth[k]``. ``truth[0]`` is the
    initial pose every method starts from.

    Attributes:
        scenario: the scenario's name.
        seed: the run's seed.
        map_id: id of the map, ``[A-Za-z0-9_-]``.
        world: the map.
        stamps_ns: ``(T,)`` scan stamps, ns since the epoch.
        truth: ``(T, 3)`` reference poses of the robot base at the scans.
        odometry: ``(T, 3)`` odometry poses at the scan stamps (odometry frame).
        scans: ``T`` scans.
        sigma: range noise used for the Cramer-Rao bound, metres.
        people: ``(T, P, 2)`` positions of the people, if any.
    """

    scenario: str
    seed: int
    map_id: str
    world: Map
    stamps_ns: IntArray
    truth: FloatArray
    odometry: FloatArray
    scans: tuple[Scan, ...]
    sigma: float
    people: FloatArray | None = None

    @property
    def updates(self) -> int:
        """Number of updates (scans after the first)."""
        return len(self.scans) - 1


def named_scenarios(steps: int = 300) -> list[Scenario]:
    """The named scenarios of the accuracy benchmark, each ``steps`` scans long."""
    heavy = OdometryModel(trans_noise=0.15, rot_noise=0.15, rot_per_metre=0.05, heading_bias=0.03)
    return [
        Scenario("nominal", "360 beams, 1 cm noise, mild odometry drift", steps=steps),
        Scenario("people", "nominal plus 8 people walking, not on the map", people=8, steps=steps),
        Scenario(
            "heavy-odometry",
            "odometry noise 15 % and heading bias 0.03 rad/m",
            odometry=heavy,
            steps=steps,
        ),
        Scenario(
            "dropouts",
            "30 % of beams return nothing",
            lidar=LidarModel(dropout=0.3),
            steps=steps,
        ),
        Scenario(
            "narrow-fov",
            "180 degree field of view, 181 beams at 1 degree",
            lidar=LidarModel(beams=181, fov=math.pi),
            steps=steps,
        ),
        Scenario(
            "range-4m",
            "nominal with a 4 m maximum range",
            lidar=LidarModel(max_range=4.0),
            steps=steps,
        ),
        Scenario(
            "lidar-270",
            "1080 beams over 270 degrees (0.25 degree steps)",
            lidar=LidarModel(beams=1080, fov=1.5 * math.pi),
            steps=steps,
        ),
        Scenario(
            "noise-3cm",
            "3 cm range noise and 10 % of beams without a return",
            lidar=LidarModel(noise=0.03, dropout=0.1),
            steps=steps,
        ),
        Scenario(
            "rooms",
            "ten small rooms off a corridor, 1.3 m doors; the path goes room to room "
            "(0.3 m clearance)",
            "rooms",
            steps=steps,
            clearance=0.3,
        ),
        Scenario("depot", "Nav2 depot map (imported grid), nominal sensor", "depot", steps=steps),
        Scenario(
            "tb3-sandbox",
            "Nav2 TurtleBot3 sandbox (imported grid), 0.3 m/s, 3.5 m range",
            "tb3_sandbox",
            lidar=LidarModel(max_range=3.5),
            steps=steps,
            speed=0.3,
            clearance=0.3,
        ),
    ]


def make_rooms(
    rng: np.random.Generator,
    rooms: int = 5,
    depth: float = 4.0,
    corridor: float = 2.4,
    door: float = 1.3,
    wall: float = 0.15,
) -> Map:
    """A corridor along x with ``rooms`` small rooms on each side, one door per room.

    Room widths are drawn in [3.2, 4.8] m and each door's place along its wall at random, so
    the rooms are alike but not identical (as in an office). The only way between two rooms
    is through the corridor.

    Args:
        rng: random generator.
        rooms: rooms on each side of the corridor.
        depth: depth of a room (across the corridor), metres.
        corridor: corridor width, metres.
        door: door width, metres.
        wall: wall thickness, metres.
    """
    widths = rng.uniform(3.2, 4.8, rooms)
    xs = np.concatenate([[0.0], np.cumsum(widths + wall)])
    length = float(xs[-1]) - wall
    height = 2.0 * depth + corridor + 2.0 * wall
    walls = []
    for wy, (ya, yb) in (
        (depth, (0.0, depth)),
        (depth + wall + corridor, (height - depth, height)),
    ):
        for i in range(rooms):
            x0, x1 = float(xs[i]), float(xs[i] + widths[i])
            d = rng.uniform(x0 + 0.3, x1 - 0.3 - door)
            walls.append(box(x0 - wall, wy, d, wy + wall))
            walls.append(box(d + door, wy, x1 + wall, wy + wall))
            if i > 0:
                walls.append(box(x0 - wall, ya, x0, yb))
    free = box(0.0, 0.0, length, height).difference(shapely.union_all(walls))
    if not isinstance(free, Polygon):
        free = max(free.geoms, key=lambda g: g.area)
    return Map.from_shapely(shapely.set_precision(free, 1e-6))


@cache
def imported_map(stem: str) -> Map:
    """A map of ``bench/data/maps`` imported with the default options (largest component).

    Depot's largest free component includes a band between the outer walls and the image
    border, reached through gaps in the walls: rays leave through those gaps as they would on
    the grid. Paths keep their clearance, so none runs in the band.
    """
    from service.maps.mapimport import import_grid

    result = import_grid(DATA / "maps" / f"{stem}.yaml")
    return Map.from_geojson(result.map["geometry"])


def world_of(scenario: Scenario, seed: int) -> tuple[str, Map]:
    """The map id and map of a scenario's run ``seed``."""
    if scenario.world == "building":
        width, height, rooms_x, rooms_y = BUILDING_SIZES[seed % len(BUILDING_SIZES)]
        rng = np.random.default_rng(seed)
        world = make_building(rng, width, height, rooms_x, rooms_y)
        return f"building-{seed}", world
    if scenario.world == "rooms":
        return f"rooms-{seed}", make_rooms(np.random.default_rng([seed, 5]))
    return scenario.world.replace("_", "-"), imported_map(scenario.world)


def simulate(scenario: Scenario, seed: int, given: tuple[str, Map] | None = None) -> Run:
    """Simulate one run of a scenario.

    Args:
        scenario: the recipe.
        seed: the run's seed; the world, path, odometry, scans and people each use
            ``default_rng([seed, part])``.
        given: ``(map_id, map)`` to use instead of the scenario's world.

    Returns:
        The run.
    """
    map_id, world = given if given is not None else world_of(scenario, seed)
    steps = scenario.steps
    truth = make_trajectory(
        world,
        np.random.default_rng([seed, 1]),
        steps,
        dt=scenario.dt,
        speed=scenario.speed,
        clearance=scenario.clearance,
    )
    odometry = drift_odometry(truth, scenario.odometry, np.random.default_rng([seed, 2]))
    scan_rng = np.random.default_rng([seed, 3])
    crowd: FloatArray | None = None
    if scenario.people:
        walk = people_walk(
            world, np.random.default_rng([seed, 4]), scenario.people, steps, scenario.dt
        )
        crowd = np.stack(list(walk))
    scans = tuple(
        simulate_scan(
            world, truth[k], scenario.lidar, scan_rng, people=None if crowd is None else crowd[k]
        )
        for k in range(steps)
    )
    stamps = T0_NS + np.round(np.arange(steps) * scenario.dt * 1e9).astype(np.int64)
    return Run(
        scenario.name,
        seed,
        map_id,
        world,
        stamps,
        truth,
        odometry,
        scans,
        scenario.lidar.noise,
        people=crowd,
    )


def with_beams(scenario: Scenario, beams: int) -> Scenario:
    """The scenario with ``beams`` beams (same field of view), renamed ``name-{beams}``."""
    lidar = replace(scenario.lidar, beams=beams)
    return replace(scenario, name=f"{scenario.name}-{beams}", lidar=lidar)
