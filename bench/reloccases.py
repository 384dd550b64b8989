"""The cases of the relocalization benchmark (:mod:`bench.relocalize`): its maps, the query
poses and scans, the grading tolerances and targets, and the ambiguity oracle."""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache

import numpy as np
import shapely
import shapely.affinity
from shapely.geometry import box

from bench.scenarios import FloatArray, imported_map
from rlutf.map import Map
from rlutf.motion import wrap_scalar
from rlutf.raycast import Beams
from rlutf.refine import RefineSettings, refine_pose
from rlutf.relocalize import RelocalizeSettings
from rlutf.scan import Scan
from rlutf.sim import (
    LidarModel,
    make_building,
    random_free_point,
    simulate_scan,
)

#: Procedural buildings ``name -> (width, height, rooms_x, rooms_y)``, about 300 to 10,000 m2.
BUILDINGS = {
    "building-300": (24.0, 14.0, 3, 2),
    "building-1000": (40.0, 25.0, 5, 3),
    "building-3000": (70.0, 42.0, 8, 5),
    "building-10000": (125.0, 80.0, 14, 9),
}
#: Imported maps with simulated scans ``name -> (map stem, lidar)``, as the tracking scenarios.
IMPORTED = {
    "depot": ("depot", LidarModel()),
    "tb3-sandbox": ("tb3_sandbox", LidarModel(max_range=3.5)),
}
#: Real logs: the map built from the log, its scans at the SLAM poses.
REAL = ("intel", "aces")
ALL_MAPS = (*BUILDINGS, *IMPORTED, *REAL)
#: Seed of the buildings' generator.
MAP_SEED = 13
#: Query poses keep this far from walls, metres.
CLEARANCE = 0.3
#: Grading: coarse and refined tolerances, (metres, degrees).
COARSE = (0.3, 5.0)
REFINED = (0.05, 1.0)
#: The oracle: a pose this far from the truth (metres, degrees) is another place ...
AWAY = (0.5, 10.0)
#: ... and fits "about as well" as the truth within this share of the beams.
MARGIN = 0.05
#: The issue's targets.
COARSE_TARGET = 0.95
REFINED_TARGET = 0.90
WRONG_TARGET = 0.01
AMBIGUOUS_TARGET = 0.95
TIME_TARGETS = (("building-1000", 1000.0, 0.5), ("building-10000", 10000.0, 2.0))
KIDNAP_SCANS = 20
KIDNAP_STAY = (0.05, 1.0)
KIDNAP_WRONG = 0.3
#: Kidnap buildings, cycled over the seeds (the tracking scenarios' sizes).
BUILDING_SIZES_KIDNAP = ((24.0, 14.0, 3, 2), (18.0, 12.0, 2, 2), (30.0, 16.0, 4, 2))

SETTINGS = {
    "default": RelocalizeSettings(),
    "turning": RelocalizeSettings(turning_rank=True),
}


@dataclass(frozen=True)
class RelocProfile:
    """How much the relocalization part runs.

    Attributes:
        name: ``full`` or ``quick``.
        queries: query poses per map.
        maps: the maps, names of :data:`ALL_MAPS`.
        kidnap_seeds: one kidnap run per seed.
        kidnap_steps: scans per kidnap run.
        kidnap_at: the scan at which the robot is teleported.
        heavy: maps that get ``heavy_queries`` instead (the slow ones, to keep the time).
        heavy_queries: see ``heavy``.
    """

    name: str
    queries: int
    maps: tuple[str, ...]
    kidnap_seeds: tuple[int, ...]
    kidnap_steps: int
    kidnap_at: int
    heavy: tuple[str, ...] = ()
    heavy_queries: int = 0

    def count(self, name: str) -> int:
        """Queries on map ``name``."""
        return self.heavy_queries if name in self.heavy else self.queries


FULL = RelocProfile(
    "full", 60, ALL_MAPS, (1, 2, 3, 4, 5, 6), 90, 30, ("building-10000", "intel", "aces"), 35
)
QUICK = RelocProfile("quick", 5, ("building-300", "tb3-sandbox"), (1,), 45, 12)


@dataclass(frozen=True, eq=False)
class MapCase:
    """A map of the benchmark and where its scans come from.

    Attributes:
        name: id in the tables.
        world: the map.
        lidar: the simulated sensor (``None``: real scans).
        scans: real scans (empty for simulated maps).
        truth: ``(S, 3)`` their SLAM poses.
    """

    name: str
    world: Map
    lidar: LidarModel | None = None
    scans: tuple[Scan, ...] = ()
    truth: FloatArray = field(default_factory=lambda: np.empty((0, 3)))

    @property
    def area(self) -> float:
        """Free area, m2."""
        return float(self.world.geometry.area)


def building(name: str) -> Map:
    """One of :data:`BUILDINGS`, with pillars and shelves in proportion to its rooms."""
    width, height, rx, ry = BUILDINGS[name]
    rooms = rx * ry
    return make_building(
        np.random.default_rng([MAP_SEED, rx, ry]),
        width,
        height,
        rx,
        ry,
        pillars=rooms,
        shelves=max(rooms // 2, 1),
    )


@cache
def map_case(name: str) -> MapCase:
    """The map ``name`` of :data:`ALL_MAPS` and its scan source."""
    if name in BUILDINGS:
        return MapCase(name, building(name), LidarModel())
    if name in IMPORTED:
        stem, lidar = IMPORTED[name]
        return MapCase(name, imported_map(stem), lidar)
    if name in REAL:
        from bench.carmen import carmen_run

        run = carmen_run(name)
        return MapCase(name, run.world, None, run.scans, run.truth)
    raise ValueError(f"unknown map {name!r}; known: {', '.join(ALL_MAPS)}")


def sample_queries(world: Map, rng: np.random.Generator, count: int) -> FloatArray:
    """``(count, 3)`` poses uniform over the free space (``CLEARANCE`` from walls), uniform
    heading."""
    out = np.empty((count, 3))
    for k in range(count):
        p = random_free_point(world, rng, CLEARANCE)
        out[k] = (p[0], p[1], rng.uniform(-math.pi, math.pi))
    return out


def queries(case: MapCase, count: int, seed: int = 0) -> list[tuple[FloatArray, Scan]]:
    """The ``(truth, scan)`` cases of a map: simulated at sampled poses, or real scans picked
    uniformly over the log (without repetition)."""
    key = zlib.crc32(case.name.encode())
    rng = np.random.default_rng([seed, 13, key])
    if case.lidar is None:
        pick = np.sort(rng.choice(len(case.scans), min(count, len(case.scans)), replace=False))
        return [(case.truth[k].copy(), case.scans[k]) for k in pick]
    poses = sample_queries(case.world, rng, count)
    scan_rng = np.random.default_rng([seed, 14, key])
    return [(p, simulate_scan(case.world, p, case.lidar, scan_rng)) for p in poses]


def close(pose: FloatArray, truth: FloatArray, metres: float, degrees: float) -> bool:
    """Whether ``pose`` is within ``metres`` and ``degrees`` of ``truth``."""
    turn = abs(wrap_scalar(float(pose[2]) - float(truth[2])))
    d = math.hypot(float(pose[0] - truth[0]), float(pose[1] - truth[1]))
    return d < metres and turn < math.radians(degrees)


@dataclass(frozen=True)
class Oracle:
    """The ambiguity ground truth of one case.

    Attributes:
        ambiguous: some pose away from the truth fits about as well.
        truth_fit: fit share refined from the truth.
        rival_fit: best fit share of a refined pose away from the truth (0 if none).
        rival: that pose, if any.
    """

    ambiguous: bool
    truth_fit: float
    rival_fit: float
    rival: FloatArray | None


def oracle(
    world: Map,
    scan: Scan,
    truth: FloatArray,
    candidates: Sequence[FloatArray],
    fit_distance: float = 0.1,
    margin: float = MARGIN,
) -> Oracle:
    """Whether a case is ambiguous: refine from the truth and from each candidate pose; a
    refined candidate at least ``AWAY`` from the truth whose fit share is at least the truth's
    minus ``margin`` makes it so."""
    valid = scan.valid()
    beams = Beams.of(scan.angles).select(valid)
    ranges = np.ascontiguousarray(scan.ranges[valid])
    settings = RefineSettings()

    def fit(pose: FloatArray):  # type: ignore[no-untyped-def]
        return refine_pose(
            world,
            np.asarray(pose, dtype=np.float64),
            beams,
            ranges,
            scan.sensor_offset,
            scan.range_max,
            settings,
            fit_distance=fit_distance,
        )

    at_truth = fit(truth).fit
    best, rival = 0.0, None
    for c in candidates:
        r = fit(c)
        if close(r.pose, truth, AWAY[0], AWAY[1]):
            continue
        if r.fit > best:
            best, rival = r.fit, r.pose.copy()
    return Oracle(rival is not None and best >= at_truth - margin, at_truth, best, rival)


def twin_rooms() -> Map:
    """Two identical rooms (a pillar in each), 10 m apart: every pose has a twin."""
    room = box(0.0, 0.0, 6.0, 4.0).difference(box(1.0, 1.0, 1.6, 1.6))
    twin = shapely.affinity.translate(room, 10.0, 0.0)
    return Map.from_shapely(shapely.MultiPolygon([room, twin]))


TWIN_TRUTH = np.array([3.5, 2.5, 0.4])
