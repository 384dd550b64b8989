"""Global relocalization: where on the whole map is a robot, from one scan and no prior?

The exact way to search a whole map is branch and bound over a precomputed multi-resolution
grid (Cartographer's FastCorrelativeScanMatcher2D, 3D-BBS): the map is rasterised once per map
version into a score grid (each cell ``exp(-d^2 / 2 s^2)`` of its distance ``d`` to the nearest
wall, as a likelihood field) and a pyramid whose level ``k`` holds the maximum of the grid over
``2^k``-wide windows. A scan's points, rotated by each heading of a step fine enough that its
far points move at most one cell, are then scored against every translation of the free space
by descending the pyramid, best bound first; a node whose bound cannot beat the ``keep``-th best
distinct pose found so far is pruned, so the answer equals brute force on the grid.

The best distinct poses are then verified and refined with the tracker's own refinement
(:mod:`rlutf.refine`) and ranked by their robust fit. A symmetric place (identical rooms, a
featureless corridor) gives several poses that fit the scan about equally well: the result
says so (:attr:`Relocalization.ambiguous`) rather than pick one, and the caller follows them
with odometry and the next scans (:class:`rlutf.Localizer`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rlutf.errors import GeometryError
from rlutf.map import Map
from rlutf.motion import compose, wrap_scalar
from rlutf.raycast import Beams
from rlutf.refine import Refinement, RefineSettings, refine_pose
from rlutf.scan import Scan, beam_points, simplify_ring
from rlutf.turning import turning_distance

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RelocalizeSettings:
    """Parameters of :func:`relocalize`.

    Attributes:
        resolution: cell side of the search grid, metres.
        depth: levels of the pyramid (the coarsest windows are ``2^(depth - 1)`` cells wide).
        sigma: width of the score grid's likelihood, metres.
        clearance: the robot's centre stays this far from walls, metres.
        max_points: the scan is thinned to at most this many points.
        max_point_range: points farther than this are left out, metres (they set the heading
            step: a far point moves a cell for a small turn).
        keep: distinct poses the search returns, verified and refined (a building of many alike
            rooms can hold more near-copies of the right place than a few, and the grid's
            discretisation may rank the right one below several of them).
        apart: poses closer than this (metres) and ``apart_heading`` are one pose.
        apart_heading: radians.
        min_score: the search keeps no pose whose mean score is under this (0 to 1).
        accept_fit: the best pose must have at least this share of its beams within
            ``fit_distance`` of the map to count as found.
        fit_distance: metres.
        ambiguity: another pose whose fit is within this of the best's (and which is ``apart``
            from it) makes the answer ambiguous.
        select_scale: Cauchy scale of the robust cost that ranks the refined poses, metres.
        turning_rank: among the poses that fit about as well as the best (``ambiguity``), rank
            by the exact turning distance (Arkin et al.) between the scan's polygon and the
            polygon cast from the pose, and call the answer ambiguous only if their turning
            distances are within ``turning_ambiguity`` too. Off by default: ``BENCHMARKS.md``
            measures what it buys.
        turning_ambiguity: see ``turning_rank``.
    """

    resolution: float = 0.1
    depth: int = 6
    sigma: float = 0.1
    clearance: float = 0.15
    max_points: int = 120
    max_point_range: float = 15.0
    keep: int = 16
    apart: float = 0.5
    apart_heading: float = math.radians(10.0)
    min_score: float = 0.3
    accept_fit: float = 0.8
    fit_distance: float = 0.1
    ambiguity: float = 0.05
    select_scale: float = 0.03
    turning_rank: bool = False
    turning_ambiguity: float = 0.05


@dataclass(frozen=True)
class Hypothesis:
    """One place the robot may be.

    Attributes:
        pose: ``(3,)`` refined pose of the robot base.
        score: share of the scan's returns within ``fit_distance`` of the map at ``pose``.
        cost: robust cost of the residuals at ``pose`` (lower is better).
    """

    pose: FloatArray
    score: float
    cost: float


@dataclass(frozen=True)
class Relocalization:
    """Outcome of :func:`relocalize`.

    Attributes:
        hypotheses: distinct poses, best first (lowest cost).
        found: the best one fits (``accept_fit``).
        ambiguous: another one fits about as well (``ambiguity``), far enough away to be
            another place.
        nodes: grid nodes and leaves scored by the search.
        refinements: the refinements of the hypotheses, in the same order.
    """

    hypotheses: tuple[Hypothesis, ...]
    found: bool
    ambiguous: bool
    nodes: int
    refinements: tuple[Refinement, ...]

    @property
    def best(self) -> Hypothesis | None:
        """The best hypothesis, if any."""
        return self.hypotheses[0] if self.hypotheses else None


#: Rows of the search grid made at once (see :func:`_make_grid`).
_BAND_ROWS = 256


@dataclass(frozen=True, eq=False)
class SearchGrid:
    """A map rasterised for the search, made once per map version (:func:`search_grid`).

    Attributes:
        levels: ``(depth, H, W)`` uint8 score pyramid.
        valid: ``(depth, H, W)`` uint8 pyramid of the cells where the robot may stand.
        origin: ``(x, y)`` of cell ``(0, 0)``'s corner, metres.
        resolution: metres.
    """

    levels: NDArray[np.uint8]
    valid: NDArray[np.uint8]
    origin: tuple[float, float]
    resolution: float

    @property
    def nbytes(self) -> int:
        """Memory held, bytes."""
        return int(self.levels.nbytes + self.valid.nbytes)


def search_grid(world: Map, settings: RelocalizeSettings) -> SearchGrid:
    """The map's search grid for these settings, made on first use and kept with the map."""
    key = f"relocalize:{settings.resolution}:{settings.depth}:{settings.sigma}:{settings.clearance}"
    return world.derived(key, lambda w: _make_grid(w, settings))


def _make_grid(world: Map, settings: RelocalizeSettings) -> SearchGrid:
    from rlutf import _bnb, _grid

    res = settings.resolution
    margin = 3.0 * settings.sigma + res
    minx, miny, maxx, maxy = world.bounds
    x0, y0 = minx - margin, miny - margin
    width = math.ceil((maxx - minx + 2 * margin) / res)
    height = math.ceil((maxy - miny + 2 * margin) / res)
    truncation = max(3.0 * settings.sigma, settings.clearance + res)
    dist = _grid.distance_field(world.segments, x0, y0, res, width, height, truncation)
    cx = x0 + (np.arange(width) + 0.5) * res
    cy = y0 + (np.arange(height) + 0.5) * res
    base = np.empty((height, width), dtype=np.uint8)
    free = np.empty((height, width), dtype=np.uint8)
    # In bands of rows: the float64 temporaries of the whole grid (about 50 bytes a cell)
    # dominated the memory of a large map's search grid.
    for r0 in range(0, height, _BAND_ROWS):
        r1 = min(r0 + _BAND_ROWS, height)
        d = dist[r0:r1]
        base[r0:r1] = np.round(
            255.0 * np.exp(-(d.astype(np.float64) ** 2) / (2.0 * settings.sigma**2))
        ).astype(np.uint8)
        gx, gy = np.meshgrid(cx, cy[r0:r1])
        inside = world.contains(np.column_stack([gx.ravel(), gy.ravel()])).reshape(r1 - r0, width)
        free[r0:r1] = (inside & (d >= settings.clearance)).astype(np.uint8)
    del dist
    levels = _bnb.pyramid(base, settings.depth)
    valid = _bnb.pyramid(free, settings.depth)
    levels.flags.writeable = False
    valid.flags.writeable = False
    return SearchGrid(levels, valid, (x0, y0), res)


def relocalize(
    world: Map,
    scan: Scan,
    region: tuple[float, float, float] | None = None,
    settings: RelocalizeSettings | None = None,
    refine: RefineSettings | None = None,
) -> Relocalization:
    """Find the robot on the whole map (or in ``region``) from one scan.

    Args:
        world: the map.
        scan: the scan.
        region: ``(x, y, radius)``: the robot is within this circle, metres.
        settings: the search; defaults to :class:`RelocalizeSettings`.
        refine: the refinement of each hypothesis; defaults to :class:`RefineSettings`.

    Returns:
        The hypotheses, best first, and whether the best one is found and unambiguous.
    """
    from rlutf import _bnb

    cfg = settings or RelocalizeSettings()
    ref = refine or RefineSettings()
    valid = scan.valid()
    beams = Beams.of(scan.angles).select(valid)
    ranges = np.ascontiguousarray(scan.ranges[valid])
    if len(ranges) < 8:
        return Relocalization((), False, False, 0, ())
    grid = search_grid(world, cfg)
    points = _thin(beam_points(ranges, beams.cos, beams.sin, scan.sensor_offset), cfg)
    if len(points) < 8:
        return Relocalization((), False, False, 0, ())
    far = float(np.max(np.hypot(points[:, 0], points[:, 1])))
    step = math.acos(max(1.0 - cfg.resolution**2 / (2.0 * max(far, cfg.resolution) ** 2), -1.0))
    turns = max(math.ceil(2.0 * math.pi / step), 8)
    headings = -math.pi + (2.0 * math.pi / turns) * np.arange(turns)
    c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
    px, py = points[:, 0][None, :], points[:, 1][None, :]
    inv = 1.0 / cfg.resolution
    cx = np.floor(0.5 + (c * px - s * py) * inv).astype(np.int64)
    cy = np.floor(0.5 + (s * px + c * py) * inv).astype(np.int64)
    if region is None:
        circle = np.array([0.0, 0.0, -1.0])
    else:
        rx, ry, radius = (float(v) for v in region)
        circle = np.array(
            [(rx - grid.origin[0]) * inv - 0.5, (ry - grid.origin[1]) * inv - 0.5, radius * inv]
        )
    totals, rots, cols, rows, nodes = _bnb.search(
        grid.levels,
        grid.valid,
        cx,
        cy,
        circle,
        math.ceil(cfg.min_score * 255 * len(points)),
        cfg.keep,
        max(round(cfg.apart * inv), 1),
        max(round(cfg.apart_heading / (2.0 * math.pi / turns)), 1),
    )
    fits: list[Refinement] = []
    for total, r, i, j in zip(totals, rots, cols, rows, strict=True):
        if total < 0:
            break
        start = np.array(
            [
                grid.origin[0] + (i + 0.5) * cfg.resolution,
                grid.origin[1] + (j + 0.5) * cfg.resolution,
                float(headings[r]),
            ]
        )
        fits.append(
            refine_pose(
                world,
                start,
                beams,
                ranges,
                scan.sensor_offset,
                scan.range_max,
                ref,
                fit_distance=cfg.fit_distance,
            )
        )
    shapes = None
    if cfg.turning_rank:
        shapes = [_turning(beams, ranges, f.ranges, scan) for f in fits]
    return rank(fits, cfg, int(nodes), shapes)


def _turning(beams: Beams, real: FloatArray, virtual: FloatArray, scan: Scan) -> float:
    """Exact turning distance between the scan's polygon and the one cast from a pose (both
    through the sensor, simplified at 3 cm); ``inf`` where either is degenerate."""
    cast = np.where(np.isfinite(virtual), virtual, scan.range_max)
    rings = []
    for r in (real, cast):
        pts = beam_points(r, beams.cos, beams.sin, np.zeros(3))
        ring = simplify_ring(np.vstack([pts, np.zeros((1, 2))]), 0.03)
        rings.append(ring)
    try:
        return float(turning_distance(rings[0], rings[1]))
    except GeometryError:
        return math.inf


def rank(
    fits: list[Refinement],
    cfg: RelocalizeSettings,
    nodes: int = 0,
    shapes: list[float] | None = None,
) -> Relocalization:
    """Hypotheses from refined poses: duplicates merged, best (lowest robust cost) first, and
    whether the best is found and unambiguous; with ``shapes`` (each fit's turning distance,
    ``turning_rank``), near-equal fits are ordered and told apart by it."""
    scored = sorted(
        ((robust_cost(f.residuals, cfg.select_scale), k, f) for k, f in enumerate(fits)),
        key=lambda t: (t[0], t[1]),
    )
    kept: list[tuple[float, int, Refinement]] = []
    for cost, k, fit in scored:
        if not any(_same(fit.pose, other.pose, 0.1, math.radians(2.0)) for _, _, other in kept):
            kept.append((cost, k, fit))
    if shapes is not None and kept:
        # Near-equal fits: the one whose polygon's shape is nearest the scan's goes first.
        top = kept[0][2].fit
        near = [t for t in kept if t[2].fit >= top - cfg.ambiguity]
        rest = [t for t in kept if t[2].fit < top - cfg.ambiguity]
        kept = sorted(near, key=lambda t: (shapes[t[1]], t[0])) + rest
    hypotheses = tuple(Hypothesis(_wrapped(f.pose), f.fit, cost) for cost, _, f in kept)
    found = bool(hypotheses) and hypotheses[0].score >= cfg.accept_fit
    ambiguous = False
    for _, k, fit in kept[1:]:
        if fit.fit < hypotheses[0].score - cfg.ambiguity:
            continue
        if _same(fit.pose, hypotheses[0].pose, cfg.apart, cfg.apart_heading):
            continue
        if shapes is not None and shapes[k] - shapes[kept[0][1]] > cfg.turning_ambiguity:
            continue
        ambiguous = True
    return Relocalization(hypotheses, found, ambiguous, nodes, tuple(f for _, _, f in kept))


def robust_cost(residuals: FloatArray, scale: float) -> float:
    """Cauchy cost ``sum log(1 + (r / scale)^2)`` of residuals; a beam that hits nothing (NaN)
    counts as off by ``4 scale``."""
    u = np.nan_to_num(residuals, nan=4.0 * scale) / scale
    return float(np.log1p(u * u).sum())


def _wrapped(pose: FloatArray) -> FloatArray:
    """A copy of ``pose`` with its heading in ``[-pi, pi)``."""
    return np.array([pose[0], pose[1], wrap_scalar(float(pose[2]))])


def _same(a: FloatArray, b: FloatArray, distance: float, heading: float) -> bool:
    turn = abs((float(a[2]) - float(b[2]) + math.pi) % (2.0 * math.pi) - math.pi)
    return math.hypot(float(a[0] - b[0]), float(a[1] - b[1])) < distance and turn < heading


def _thin(points: FloatArray, cfg: RelocalizeSettings) -> FloatArray:
    """At most ``max_points`` points within ``max_point_range``, evenly along the scan."""
    near = points[np.hypot(points[:, 0], points[:, 1]) <= cfg.max_point_range]
    if len(near) > cfg.max_points:
        pick = np.linspace(0, len(near) - 1, cfg.max_points).round().astype(np.int64)
        near = near[pick]
    return np.ascontiguousarray(near)


@dataclass(frozen=True)
class FollowSettings:
    """How :class:`Follower` decides between hypotheses over several scans.

    Attributes:
        max_hypotheses: most hypotheses followed.
        min_fit: a hypothesis whose refined pose has fewer of a scan's returns within
            ``fit_distance`` is dropped.
        accept_fit: the winner must fit at least this share of the scan's returns.
        win_margin: the winner's summed unfit share (over the scans followed) must be at least
            this much under every other hypothesis's.
        follow_scans: after this many scans without a winner, search the map again.
        widen_after: a search in a region that has no winner after this many scans searches the
            whole map from its next search on (the robot is not where it was said to be); 0:
            never.
    """

    max_hypotheses: int = 5
    min_fit: float = 0.5
    accept_fit: float = 0.8
    win_margin: float = 0.3
    follow_scans: int = 10
    widen_after: int = 0


@dataclass
class _Followed:
    pose: FloatArray
    fit: Refinement
    miss: float


@dataclass(frozen=True)
class FollowStep:
    """What one scan of a relocalization gave.

    Attributes:
        winner: the refinement of the hypothesis that won, if one did on this scan.
        hypotheses: the hypotheses still followed, best first (empty with a winner).
        best: the refinement of the best hypothesis (the winner's, with one).
        nodes: grid nodes scored by the search.
    """

    winner: Refinement | None
    hypotheses: tuple[Hypothesis, ...]
    nodes: int
    best: Refinement | None


class Follower:
    """A relocalization over several scans: search the map, then follow the hypotheses with
    odometry and the next scans until one wins clearly.

    Args:
        world: the map.
        region: ``(x, y, radius)`` the robot is in, or ``None`` for the whole map.
        search: the map search's parameters.
        follow: how hypotheses are followed and decided.
        refine: the refinement's parameters.
    """

    def __init__(
        self,
        world: Map,
        region: tuple[float, float, float] | None,
        search: RelocalizeSettings,
        follow: FollowSettings,
        refine: RefineSettings,
    ) -> None:
        self.world = world
        self.region = region
        self._search = search
        self._follow = follow
        self._refine = refine
        self._followed: list[_Followed] = []
        self._scans = 0
        self._steps = 0  # scans taken since the relocalization began

    def step(
        self, motion: FloatArray, scan: Scan, fit: Callable[[FloatArray], Refinement]
    ) -> FollowStep:
        """Take the motion since the previous scan and the new scan.

        ``fit(pose)`` refines a pose against this scan (the localizer's own refinement).
        """
        cfg = self._follow
        self._steps += 1
        if self._followed:
            self._scans += 1
            moved = []
            for h in self._followed:
                refined = fit(compose(h.pose, motion))
                if refined.fit >= cfg.min_fit:
                    moved.append(_Followed(refined.pose, refined, h.miss + 1.0 - refined.fit))
            moved.sort(key=lambda h: h.miss)
            kept: list[_Followed] = []
            for h in moved:  # two hypotheses that ran into one place are one
                if not any(_same(h.pose, k.pose, 0.1, math.radians(2.0)) for k in kept):
                    kept.append(h)
            self._followed = kept
            if kept:
                best = kept[0]
                clear = len(kept) == 1 or kept[1].miss - best.miss >= cfg.win_margin
                if clear and best.fit.fit >= cfg.accept_fit:
                    self._followed = []
                    return FollowStep(best.fit, (), 0, best.fit)
                if self._scans < cfg.follow_scans:
                    return FollowStep(None, self._hypotheses(), 0, kept[0].fit)
        # Search the map: the first scan, or every hypothesis failed, or none won in time.
        if self.region is not None and 0 < cfg.widen_after < self._steps:
            self.region = None  # nothing in the region won: before, it was searched for good
        found = relocalize(self.world, scan, self.region, self._search, self._refine)
        self._scans = 0
        if found.found and not found.ambiguous:
            self._followed = []
            return FollowStep(found.refinements[0], (), found.nodes, found.refinements[0])
        self._followed = [
            _Followed(f.pose.copy(), f, 1.0 - f.fit)
            for f in found.refinements[: cfg.max_hypotheses]
            if f.fit >= cfg.min_fit
        ]
        best_fit = found.refinements[0] if found.refinements else None
        return FollowStep(None, self._hypotheses(), found.nodes, best_fit)

    def _hypotheses(self) -> tuple[Hypothesis, ...]:
        scale = self._search.select_scale
        return tuple(
            Hypothesis(_wrapped(h.pose), h.fit.fit, robust_cost(h.fit.residuals, scale))
            for h in self._followed
        )
