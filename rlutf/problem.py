"""One update's comparison: the real scan, its polygon, the beams to cast, and the search's
scorer (see :mod:`rlutf.localizer`)."""

from __future__ import annotations

import copy

import numpy as np
from numpy.typing import NDArray

from rlutf.config import LocalizerConfig
from rlutf.discrepancy import PolarArea, anchored_turning, turning_steps
from rlutf.map import Map
from rlutf.motion import compose
from rlutf.raycast import Beams
from rlutf.scan import Scan, beam_points, simplify_ring
from rlutf.search import RandomSearch

FloatArray = NDArray[np.float64]


class Problem:
    """What one update compares against: the real scan, its polygon and the beams to cast."""

    def __init__(self, world: Map, scan: Scan, config: LocalizerConfig, beams: Beams) -> None:
        from rlutf import _kernels

        self.world = world
        self.config = config
        self.offset = np.ascontiguousarray(scan.sensor_offset, dtype=np.float64)
        self.scan_range = scan.range_max
        self.range_max = scan.range_max
        kind = config.discrepancy
        self.cap = config.area_cap if kind == "area" else None
        cap = self.cap if self.cap is not None else 0.0
        self.count, self.closing, terms, longest = _kernels.scan_terms(
            scan.ranges,
            beams.angles,
            beams.cos,
            beams.sin,
            scan.range_min,
            scan.range_max,
            scan.covers_full_circle(),
            config.max_gap,
            cap,
        )
        if self.count < config.min_returns:
            return
        # The rows of terms: weights, angles, cosines, sines, ranges, squared ranges, band.
        self.beams = beams if self.count == len(beams) else Beams(terms[1], terms[2], terms[3])
        self.real_ranges = real = terms[4]
        if kind != "turning":
            # The combined discrepancy keeps the exact area: capped, its turning term (which
            # people and grazed edges disturb the most) would dominate.
            given = terms[6] if cap > 0.0 else None
            self.area = PolarArea.of_terms(real, terms[0], self.cap, terms[5], given)
        if self.cap is not None:
            # A virtual range past the real one plus the cap counts as the cap, so no beam needs
            # casting farther than the longest return plus the widest cap of a search.
            widest = max(self.cap, config.cap_per_radius * 2.0 * config.delta)
            self.range_max = min(self.range_max, longest + widest)
        if kind != "area":
            points = beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)
            ring = np.vstack([points, self.offset[None, :2]]) if self.closing else points
            self.real_steps = turning_steps(simplify_ring(ring, config.simplify_tolerance))

    def on(self, world: Map) -> Problem:
        """The same comparison against another version of the walls (a shallow copy)."""
        other = copy.copy(self)
        other.world = world
        return other

    def area_terms(self) -> tuple[FloatArray, FloatArray, FloatArray, float] | None:
        """The capped polar area's terms for :func:`rlutf.refine.refine_pose`, if the
        discrepancy is the capped area."""
        if self.cap is None:
            return None
        area = self.area
        return (area.weights, area.real_sq, area.band(self.cap), self.range_max)

    def points(self) -> FloatArray:
        """``(n, 2)`` the scan's returns in the base frame."""
        return beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)

    def score(self, poses: FloatArray, cap: float | None = None) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, 3)`` poses; ``inf`` outside the free space.

        ``cap`` replaces the configured area cap (capped area only)."""
        inside = self.world.contains(poses[:, :2])
        out = np.full(len(poses), np.inf)
        if inside.any():
            out[inside] = self._discrepancy(np.ascontiguousarray(poses[inside]), cap)
        return out

    def _discrepancy(self, poses: FloatArray, cap: float | None) -> FloatArray:
        from rlutf import _kernels

        kind = self.config.discrepancy
        if kind == "area":
            area = self.area
            caps = area.band(cap if cap is not None else self.cap)
            return _kernels.score_area(
                poses,
                self.offset,
                self.beams.cos,
                self.beams.sin,
                area.real_sq,
                area.weights,
                caps,
                self.range_max,
                *self.world.grid,
            )
        sensors = np.ascontiguousarray(compose(poses, self.offset))
        ranges, _ = _kernels.cast_poses(
            sensors, self.beams.cos, self.beams.sin, self.range_max, True, *self.world.grid
        )
        np.minimum(ranges, self.range_max, out=ranges)
        return self.of_ranges(ranges)

    def of_ranges(self, ranges: FloatArray, cap: float | None = None) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, n)`` virtual ranges (``inf`` past the range)."""
        r = np.minimum(ranges, self.range_max)
        kind = self.config.discrepancy
        if kind == "area":
            return self.area(r, cap if cap is not None else self.cap)
        rings = beam_points(r, self.beams.cos, self.beams.sin, self.offset)
        if self.closing:
            origin = np.broadcast_to(self.offset[:2], (len(r), 1, 2))
            rings = np.concatenate([rings, origin], axis=1)
        d = anchored_turning(
            turning_steps(rings), self.real_steps, normalise=self.config.mode == "paper"
        )
        if kind == "combined":
            d = d + self.config.area_weight * self.area(r)
        return d


class Scorer:
    """A search's comparison: the problem's discrepancy, with the area's cap widened to the
    round's radius when ``widen = (cap, per_radius)`` is given. When the cap changes between
    rounds, the best pose so far is scored again under the new cap, so that a round's
    candidates and the best they must beat are compared alike."""

    def __init__(
        self, problem: Problem, search: RandomSearch, widen: tuple[float, float] | None
    ) -> None:
        self._problem = problem
        self._search = search
        self._widen = widen
        self._cap: float | None = None if widen is None else widen[0]

    def __call__(self, poses: FloatArray) -> FloatArray:
        if self._widen is None:
            return self._problem.score(poses)
        cap = max(self._widen[0], self._widen[1] * self._search.delta)
        if cap != self._cap:
            self._cap = cap
            search = self._search
            search.best_d = float(self._problem.score(search.best[None], cap)[0])
        return self._problem.score(poses, cap)
