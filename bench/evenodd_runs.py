"""The runs of :mod:`bench.evenodd`: the map of a log's even scans, its odd scans, the raw points.

See :mod:`bench.evenodd` for the check. Everything here is cached per log: the even scans, the
maps per recipe, the raw points.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cache

import numpy as np
import shapely
from scipy.spatial import cKDTree

from bench.baselines.common import Estimate
from bench.baselines.icp import IcpConfig, PointToLineIcp, WallSamples, point_samples
from bench.carmen import ODOM5_SEED, RANGE_MAX, carmen_run, slam_odometry
from bench.methods import Method, RlutfTracker, Trace, track
from bench.scenarios import DATA, FloatArray, IntArray, Run
from bench.wallfit import WallFit, fit_walls
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map, geometry_from_geojson
from rlutf.problem import Problem
from rlutf.raycast import Beams
from rlutf.refine import refine_pose
from rlutf.scan import Scan
from service.maps.mapimport.grid import OccupancyGrid

LOGS = ("intel", "aces")
#: Updates further off than this count as diverged, metres.
DIVERGED_M = 0.5
#: The raw points' thinning, metres.
RAW_SPACING = 0.02
#: ICP settings on the raw points: the accuracy benchmark's, and two with a wider first gate
#: (the odd scans are up to 2 m and 80 degrees apart, the prediction up to 0.3 m off).
ICP_SETTINGS: dict[str, IcpConfig] = {
    "bench settings": IcpConfig(),
    "gate 1 m, Huber 5 cm, 50 steps": IcpConfig(max_iterations=50, max_distance=1.0, huber=0.05),
    "gate 2 m to 0.2 m, 50 steps": IcpConfig(max_iterations=50, max_distance=2.0, min_distance=0.2),
}


@dataclass(frozen=True)
class MapRecipe:
    """How the map is built from the even scans (the defaults are ``rlutf map build``'s).

    Attributes:
        resolution: cell size, metres.
        surface_cells: walls moved this many cells into the occupied cells.
        simplify: Douglas-Peucker tolerance, metres; ``None``: half a cell.
        free_thresh: hit ratio under which a cell is free.
        occupied_thresh: hit ratio over which a cell is occupied (cells in between are
            unknown, and unknown cells are walls).
        fit: if set, the traced walls are then moved onto the even scans' hit points
            (:func:`bench.wallfit.fit_walls`; the hits in free cells are left out).
    """

    resolution: float = 0.05
    surface_cells: float = 0.4
    simplify: float | None = None
    free_thresh: float = 0.25
    occupied_thresh: float = 0.65
    fit: WallFit | None = None


@dataclass(frozen=True)
class Variant:
    """One row of the variants table: a map recipe and localizer settings."""

    label: str
    recipe: MapRecipe = field(default_factory=MapRecipe)
    config: LocalizerConfig = field(default_factory=LocalizerConfig)


def variants() -> list[Variant]:
    """The default, then one change at a time."""
    base = MapRecipe()
    return [
        Variant("default (as `rlutf map build` writes it, `LocalizerConfig()`)"),
        Variant(
            "tracked on the map as built (`coarse_tolerance=0`, the localizer before 0.4)",
            config=LocalizerConfig(coarse_tolerance=0.0),
        ),
        Variant(
            "tracked on walls simplified at 5 cm", config=LocalizerConfig(coarse_tolerance=0.05)
        ),
        Variant(
            "tracked on walls simplified at 10 cm", config=LocalizerConfig(coarse_tolerance=0.1)
        ),
        Variant("walls at the cell edges (surface offset 0)", replace(base, surface_cells=0.0)),
        Variant("surface offset 0.2 cell", replace(base, surface_cells=0.2)),
        Variant("surface offset 0.45 cell", replace(base, surface_cells=0.45)),
        Variant("simplify 0.25 cell", replace(base, simplify=0.0125)),
        Variant("simplify 1 cell", replace(base, simplify=0.05)),
        Variant("cells 2.5 cm", replace(base, resolution=0.025)),
        Variant("cells 4 cm", replace(base, resolution=0.04)),
        Variant(
            "no unknown band (free under 0.5, occupied over 0.5)",
            replace(base, free_thresh=0.5, occupied_thresh=0.5),
        ),
        Variant("refinement: 30 casts", config=LocalizerConfig(refine_iterations=30)),
        Variant("refinement: noise floor 1 cm", config=LocalizerConfig(noise_min=0.01)),
        Variant("refinement: incidence up to 60 deg", config=LocalizerConfig(max_incidence=1.047)),
    ]


def log_path(name: str) -> str:
    """The CARMEN log of ``name`` (``DATA/carmen/{name}-corrected.log.gz``)."""
    return str(DATA / "carmen" / f"{name}-corrected.log.gz")


@cache
def _even_scans(name: str) -> tuple:  # type: ignore[type-arg]
    from service.maps.mapimport import read_carmen

    return read_carmen(log_path(name)).scans[0::2]


@cache
def _grid(
    name: str, resolution: float, free_thresh: float, occupied_thresh: float
) -> OccupancyGrid:
    from service.maps.mapimport import build_grid

    return build_grid(
        _even_scans(name),
        resolution=resolution,
        free_thresh=free_thresh,
        occupied_thresh=occupied_thresh,
    )


def _wall_hits(name: str, grid: OccupancyGrid) -> tuple[FloatArray, FloatArray]:
    """The even scans' hit points in cells of ``grid`` that are not free, and their sensors."""
    points, sensors, _ = _raw_cloud(name)
    cell = np.floor(grid.to_local(points) / grid.resolution).astype(np.int64)
    walls = ~grid.free[cell[:, 1], cell[:, 0]]
    return points[walls], sensors[walls]


@cache
def even_map(name: str, recipe: MapRecipe = MapRecipe()) -> Map:
    """The map of ``name``'s even scans, built as ``rlutf map build`` builds a log's."""
    from service.maps.mapimport import grid_to_map

    grid = _grid(name, recipe.resolution, recipe.free_thresh, recipe.occupied_thresh)
    offset = recipe.surface_cells * recipe.resolution
    built = grid_to_map(grid, map_id=name, surface_offset=offset, simplify=recipe.simplify)
    if recipe.fit is None:
        return Map.from_geojson(built.map["geometry"])
    geometry = geometry_from_geojson(built.map["geometry"])
    hits, sensors = _wall_hits(name, grid)
    return Map.from_shapely(fit_walls(geometry, hits, sensors, recipe.fit))


def hit_to_wall(name: str, world: Map) -> float:
    """Median distance (cm) from the hits in the cells of the default grid that are not free to
    the nearest wall of ``world``."""
    base = MapRecipe()
    hits, _ = _wall_hits(name, _grid(name, base.resolution, base.free_thresh, base.occupied_thresh))
    segments = shapely.linestrings(world.segments.reshape(-1, 2, 2))
    _, distance = shapely.STRtree(segments).query_nearest(
        shapely.points(hits), return_distance=True, all_matches=False
    )
    return 100.0 * float(np.median(distance))


@cache
def _raw_cloud(name: str) -> tuple[FloatArray, FloatArray, IntArray]:
    """The even scans' end points at their corrected poses, their sensors and even-scan index."""
    points, sensors, scans = [], [], []
    for j, s in enumerate(_even_scans(name)):
        ok = np.isfinite(s.ranges) & (s.ranges > 0.0) & (s.ranges < RANGE_MAX)
        heading = s.pose[2] + s.angles[ok]
        ends = s.pose[:2] + s.ranges[ok, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        points.append(ends)
        sensors.append(np.broadcast_to(s.pose[:2], ends.shape))
        scans.append(np.full(len(ends), j, dtype=np.int64))
    return np.vstack(points), np.vstack(sensors), np.concatenate(scans)


@cache
def raw_points(name: str, spacing: float = RAW_SPACING) -> WallSamples:
    """The even scans' end points at their corrected poses, one per ``spacing`` cell."""
    points, sensors, _ = _raw_cloud(name)
    return point_samples(points, sensors, spacing)


@cache
def raw_points_by_scan(name: str, spacing: float = RAW_SPACING) -> tuple[WallSamples, IntArray]:
    """The even scans' points thinned per scan (one per ``spacing`` cell of each scan), with the
    even-scan index of each, so that scans can be left out."""
    points, sensors, scans = _raw_cloud(name)
    cell = np.floor(points / spacing).astype(np.int64)
    _, first = np.unique(np.column_stack([cell, scans]), axis=0, return_index=True)
    first.sort()
    samples = point_samples(points[first], sensors[first], spacing=1e-6)
    return samples, scans[first][samples.walls]


class LeaveOutIcp:
    """ICP on the raw points without the even scans next to the tracked odd scan.

    Update ``k`` of an odd run tracks scan ``2k + 1`` of the log, between even scans ``k`` and
    ``k + 1`` (even-scan indices); the even scans ``k - window + 1 .. k + window`` are left out
    of its map (``window`` 1: the scan just before and the one just after).
    """

    def __init__(self, name: str, pose: FloatArray, config: IcpConfig, window: int) -> None:
        self._samples, self._scans = raw_points_by_scan(name)
        self._icp = PointToLineIcp(None, pose, config, self._samples)
        self._window = window
        self._k = 0

    def samples_for(self, k: int) -> WallSamples:
        """The map of update ``k``."""
        keep = (self._scans < k - self._window + 1) | (self._scans > k + self._window)
        s = self._samples
        pts = s.points[keep]
        return WallSamples(pts, s.normals[keep], s.walls[keep], cKDTree(pts))

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """One ICP update on the map without the neighbouring even scans."""
        self._k += 1
        self._icp._walls = self.samples_for(self._k)
        return self._icp.update(motion, scan)


@cache
def odd_base(name: str) -> Run:
    run = carmen_run(name, world=even_map(name))
    odd = np.arange(1, len(run.scans), 2)
    return replace(
        run,
        scenario=f"{name}-odd",
        stamps_ns=run.stamps_ns[odd],
        truth=run.truth[odd],
        odometry=run.odometry[odd],
        scans=tuple(run.scans[i] for i in odd),
    )


def odd_run(name: str, world: Map, seed: int = ODOM5_SEED) -> Run:
    """The odd scans of ``name`` on ``world``, odometry from :data:`bench.carmen.ODOM5`."""
    base = odd_base(name)
    return replace(base, seed=seed, world=world, odometry=slam_odometry(base.truth, seed=seed))


@dataclass(frozen=True)
class Errors:
    """Position errors of one method over its runs, cm."""

    errors: FloatArray

    @property
    def rmse(self) -> float:
        """Root mean square."""
        return float(np.sqrt(np.mean(self.errors**2)))

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile."""
        return float(np.percentile(self.errors, q))

    @property
    def diverged(self) -> float:
        """Share of updates over :data:`DIVERGED_M` off."""
        return float(np.mean(self.errors > 100.0 * DIVERGED_M))


def _errors(trace: Trace, run: Run) -> FloatArray:
    e = np.hypot(*(trace.poses[:, :2] - run.truth[1:, :2]).T) * 100.0
    return np.where(np.isfinite(e), e, np.inf)


def rlutf_method(config: LocalizerConfig) -> Method:
    """RLuTF with ``config`` as a tracking method."""
    return Method("rlutf", "RLuTF", lambda w, p, s: RlutfTracker(w, p, config, s))


def icp_method(name: str, config: IcpConfig) -> Method:
    """Point-to-line ICP on ``name``'s raw even-scan points."""
    samples = raw_points(name)
    return Method("icp-raw", "ICP", lambda w, p, s: PointToLineIcp(None, p, config, samples))


class CoarseToFine:
    """RLuTF tracking on a coarser map, each pose then refined on the map itself.

    A trial of a localizer that converges on walls simplified at ``coarse`` (fewer small
    steps and bumps, fewer local minima) and takes its answer from the refinement on the map
    as built; the refined pose is where the next update predicts from. Since 0.4 the
    localizer does this by itself (``LocalizerConfig.coarse_tolerance``); the trial runs with
    it off.
    """

    def __init__(
        self, world: Map, pose: FloatArray, config: LocalizerConfig, seed: int, coarse: Map
    ) -> None:
        from rlutf.localizer import Localizer

        self._coarse = Localizer(coarse, pose, config, seed=seed)
        self._world = world
        self._config = config
        self._settings = config.refine_settings()

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Track on the coarse map, refine on the map."""
        result = self._coarse.update(motion, scan)
        problem = Problem(self._world, scan, self._config, Beams.of(scan.angles))
        fit = refine_pose(
            self._world, result.pose, problem.beams, problem.real_ranges, problem.offset,
            problem.scan_range, self._settings, fit_distance=self._config.fit_distance,
        )  # fmt: skip
        self._coarse._pose = fit.pose.copy()
        return Estimate(fit.pose.copy(), result.status, fit.covariance)


def coarse_to_fine_method(name: str, coarse: MapRecipe) -> Method:
    """:class:`CoarseToFine` on ``name``'s map, the coarse map built with ``coarse``."""
    coarse_map = even_map(name, coarse)

    def make(world: Map, pose: FloatArray, seed: int) -> CoarseToFine:
        config = LocalizerConfig(coarse_tolerance=0.0)
        return CoarseToFine(world, pose, config, seed, coarse_map)

    return Method("coarse-to-fine", "RLuTF coarse to fine", make)


def answer_on_method(name: str) -> Method:
    """RLuTF (``LocalizerConfig()``) tracking on ``name``'s map as built, each pose refined on
    the map it is given (:class:`CoarseToFine`)."""
    built = even_map(name)

    def make(world: Map, pose: FloatArray, seed: int) -> CoarseToFine:
        return CoarseToFine(world, pose, LocalizerConfig(), seed, built)

    return Method("answer-on", "RLuTF, answer on another map", make)


class RawAnswer:
    """RLuTF tracking on the map, each pose then aligned by ICP on the raw points (a trial of
    keeping the log's points beside the walls for the answer); the aligned pose is where the
    next update predicts from."""

    def __init__(self, world: Map, pose: FloatArray, seed: int, samples: WallSamples) -> None:
        from rlutf.localizer import Localizer

        self._loc = Localizer(world, pose, LocalizerConfig(), seed=seed)
        self._samples = samples
        self._icp = ICP_SETTINGS["gate 2 m to 0.2 m, 50 steps"]

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Track on the map, align on the raw points."""
        result = self._loc.update(motion, scan)
        aligned = PointToLineIcp(None, result.pose, self._icp, self._samples)
        pose = aligned.update(np.zeros(3), scan).pose
        if pose is None:
            return Estimate(result.pose.copy(), result.status, None)
        self._loc._pose = pose.copy()
        return Estimate(pose.copy(), result.status, None)


def raw_answer_method(name: str) -> Method:
    """:class:`RawAnswer` on ``name``'s raw even-scan points."""
    samples = raw_points(name)
    return Method(
        "raw-answer",
        "RLuTF, answer on the raw points",
        make=lambda w, p, s: RawAnswer(w, p, s, samples),
    )


def leave_out_method(name: str, config: IcpConfig, window: int) -> Method:
    """ICP on ``name``'s raw points without the even scans around each tracked one."""

    def make(world: Map, pose: FloatArray, seed: int) -> LeaveOutIcp:
        return LeaveOutIcp(name, pose, config, window)

    return Method("icp-leave-out", "ICP", make)


def update_seconds(config: LocalizerConfig, run: Run) -> list[float]:
    """Wall-clock seconds of each ``Localizer.update`` tracking ``run`` with ``config``."""
    from rlutf.localizer import Localizer
    from rlutf.motion import relative

    loc = Localizer(run.world, run.truth[0], config, seed=run.seed)
    out = []
    for k in range(1, len(run.scans)):
        motion = relative(run.odometry[k - 1], run.odometry[k])
        t0 = time.perf_counter()
        loc.update(motion, run.scans[k])
        out.append(time.perf_counter() - t0)
    return out


def tracked(method: Method, name: str, world: Map, seeds: Sequence[int]) -> Errors:
    """``method`` tracking ``name``'s odd scans on ``world``, errors pooled over ``seeds``."""
    out = []
    for seed in seeds:
        run = odd_run(name, world, seed)
        out.append(_errors(track(method, run, seed=seed), run))
    return Errors(np.concatenate(out))


#: A refinement of scan ``k`` of the odd run from a start pose: the settled pose.
Refiner = Callable[[int, Scan, FloatArray], FloatArray]


def rlutf_refiner(world: Map, config: LocalizerConfig) -> Refiner:
    """The localizer's refinement with ``config`` on ``world``."""
    settings = config.refine_settings()
    beams: list[Beams] = []

    def refine(k: int, scan: Scan, start: FloatArray) -> FloatArray:
        if not beams:
            beams.append(Beams.of(scan.angles))
        p = Problem(world, scan, config, beams[0])
        fit = refine_pose(
            world, start, p.beams, p.real_ranges, p.offset, p.scan_range, settings,
            fit_distance=config.fit_distance,
        )  # fmt: skip
        return np.asarray(fit.pose)

    return refine


def icp_refiner(name: str, config: IcpConfig, window: int = 0) -> Refiner:
    """ICP on the raw points (``window`` > 0: without the even scans around the scan, as
    :class:`LeaveOutIcp`); a pose it cannot align is infinitely off."""
    leave = LeaveOutIcp(name, odd_base(name).truth[0], config, window) if window else None

    def refine(k: int, scan: Scan, start: FloatArray) -> FloatArray:
        samples = raw_points(name) if leave is None else leave.samples_for(k)
        pose = PointToLineIcp(None, start, config, samples).update(np.zeros(3), scan).pose
        return np.full(3, np.inf) if pose is None else np.asarray(pose)

    return refine


def at_reference(run: Run, refine: Refiner) -> Errors:
    """Each odd scan of ``run`` refined once from its corrected pose (no tracking), cm off."""
    out = [
        math.hypot(*(refine(k, run.scans[k], run.truth[k])[:2] - run.truth[k, :2])) * 100.0
        for k in range(1, len(run.scans))
    ]
    return Errors(np.asarray(out))


def from_reference(name: str, world: Map, config: LocalizerConfig) -> Errors:
    """Each odd scan refined once from its corrected pose on ``world`` (no tracking)."""
    return at_reference(odd_run(name, world), rlutf_refiner(world, config))


def icp_from_reference(name: str, config: IcpConfig, window: int = 0) -> Errors:
    """ICP on the raw points, each odd scan aligned once from its corrected pose (``window``
    > 0: without the even scans around it, as :class:`LeaveOutIcp`)."""
    return at_reference(odd_base(name), icp_refiner(name, config, window))
