"""Pose-sensitive discrepancies between a virtual scan polygon ``Pv`` and the real one ``Pr``.

Arkin's turning distance (:mod:`rlutf.turning`) is invariant to translation and rotation, which is
what shape matching wants and what pose tracking must not have: in a convex room every position
gives the same shape. The localizer instead compares polygons that share a frame (the robot's)
and a start point (the first beam with a return):

* :func:`anchored_turning` -- the L2 difference of the two turning functions with the start point
  fixed at the anchor, no rotation minimisation (the absolute edge directions carry the heading)
  and metric arc length (which carries the distances to the walls). With ``normalise=True`` the
  arc length is divided by the perimeter, the paper's eq. 2.1 read literally.
* :func:`polar_area` -- the area between the two polygons divided by the real polygon's
  perimeter: a mean distance in metres; optionally each beam's share capped, so that a beam
  grazing an edge or hitting something not on the map cannot dominate (:class:`PolarArea`).

Both score ``K`` candidate polygons against one real polygon in a single vectorised call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
#: Edges shorter than this (metres) carry no direction and inherit the previous edge's.
_MIN_EDGE = 1e-9
_NO_CAP = np.empty(0)


@dataclass(frozen=True, eq=False)
class TurningSteps:
    """Turning functions of ``K`` rings as step functions of arc length.

    Attributes:
        breaks: ``(K, n + 1)`` arc length at each vertex, from 0 to the perimeter, metres.
        values: ``(K, n)`` tangent direction on each edge, radians, unwrapped from the first
            edge's absolute direction.
    """

    breaks: FloatArray
    values: FloatArray

    @property
    def perimeter(self) -> FloatArray:
        """``(K,)`` perimeters in metres."""
        return self.breaks[:, -1]


def turning_steps(rings: FloatArray) -> TurningSteps:
    """Anchored turning functions of rings that start at their anchor vertex.

    Args:
        rings: ``(K, n, 2)`` vertices of ``K`` closed rings (closing vertex not repeated), or one
            ring ``(n, 2)``.

    Returns:
        The step functions; direction of a zero-length edge is that of the edge before it.
    """
    r = rings if rings.ndim == 3 else rings[None]
    edges = np.roll(r, -1, axis=1) - r
    lengths = np.hypot(edges[..., 0], edges[..., 1])
    phi = np.arctan2(edges[..., 1], edges[..., 0])
    short = lengths < _MIN_EDGE
    if short.any():
        idx = np.where(short, 0, np.arange(phi.shape[1]))
        np.maximum.accumulate(idx, axis=1, out=idx)
        phi = np.take_along_axis(phi, idx, axis=1)
    turns = np.diff(phi, axis=1)
    turns -= _TWO_PI * np.round(turns / _TWO_PI)
    values = np.empty_like(phi)
    values[:, 0] = phi[:, 0]
    np.cumsum(turns, axis=1, out=values[:, 1:])
    values[:, 1:] += phi[:, :1]
    breaks = np.zeros((r.shape[0], r.shape[1] + 1))
    np.cumsum(lengths, axis=1, out=breaks[:, 1:])
    return TurningSteps(breaks, values)


def anchored_turning(
    virtual: TurningSteps, real: TurningSteps, *, normalise: bool = False
) -> FloatArray:
    """RMS difference of anchored turning functions, one value per virtual ring.

    The functions are compared over ``[0, L]`` with ``L`` the longer of the two perimeters; the
    shorter one keeps its last direction past its end, so a perimeter mismatch costs too.

    Args:
        virtual: ``K`` virtual rings.
        real: one real ring.
        normalise: divide arc length by each perimeter first (the paper's eq. 2.1).

    Returns:
        ``(K,)`` discrepancies in radians (RMS angle difference along the boundary).
    """
    bv, vv = virtual.breaks, virtual.values
    br, vr = real.breaks[0], real.values[0]
    k_count, nv = vv.shape
    if normalise:
        bv = bv / np.maximum(bv[:, -1:], _MIN_EDGE)
        br = br / max(float(br[-1]), _MIN_EDGE)
    length = np.maximum(bv[:, -1], br[-1])
    merged = np.sort(np.concatenate([bv, np.broadcast_to(br, (k_count, len(br)))], axis=1), axis=1)
    widths = np.diff(merged, axis=1)
    mids = merged[:, :-1] + 0.5 * widths
    # Row-wise searchsorted in one call: shift each row into its own disjoint range.
    span = float(length.max()) + 1.0
    shift = (np.arange(k_count) * span)[:, None]
    iv = np.searchsorted((bv + shift).ravel(), (mids + shift).ravel(), side="right")
    iv = iv.reshape(k_count, -1) - 1 - (np.arange(k_count) * (nv + 1))[:, None]
    np.clip(iv, 0, nv - 1, out=iv)
    ir = np.clip(np.searchsorted(br, mids, side="right") - 1, 0, len(vr) - 1)
    diff = np.take_along_axis(vv, iv, axis=1) - vr[ir]
    integral = np.einsum("kn,kn->k", widths, diff * diff)
    return np.asarray(
        np.sqrt(np.maximum(integral, 0.0) / np.maximum(length, _MIN_EDGE)), dtype=np.float64
    )


class PolarArea:
    """:func:`polar_area` against one real scan, prepared for scoring many virtual scans.

    The trapezoid rule makes the area a fixed weighted sum of ``|rho_v^2 - rho_r^2|`` over the
    beams, so what depends only on the real scan (its squared ranges, the weights and its
    perimeter) is computed once.

    Args:
        real_ranges: ``(n,)`` measured ranges, metres.
        angles: ``(n,)`` beam angles in scan order, radians.
        closing: the polygons close through the sensor, so the sector between the last beam and
            the first is not part of them.
        cap: if given, each beam's sector counts as at most a band of this width (metres) along
            the real range: ``|rho_v^2 - rho_r^2|`` is clipped at ``2 cap rho_r``. A beam that
            grazes an edge and jumps to a far wall, or hits a person who is not on the map, then
            weighs no more than a ``cap`` error, which keeps the discrepancy continuous enough to
            search. ``None`` gives the exact area.
        unit: ``(n,)`` beam directions ``exp(i angles)``, if at hand.
        gaps: ``(n - 1,)`` angles between consecutive beams ``|diff(angles)|``, if at hand.
    """

    def __init__(
        self,
        real_ranges: FloatArray,
        angles: FloatArray,
        closing: bool,
        cap: float | None = None,
        *,
        unit: NDArray[np.complex128] | None = None,
        gaps: FloatArray | None = None,
    ) -> None:
        n = len(angles)
        if gaps is None:
            gaps = np.abs(angles[1:] - angles[:-1])
        if unit is None:
            unit = np.exp(1j * angles)
        points = real_ranges * unit
        steps = points[1:] - points[:-1]
        perimeter = float(np.add.reduce(np.abs(steps)))
        wrap = 0.0
        if not closing and n > 1:
            wrap = _TWO_PI - abs(float(angles[-1] - angles[0]))
            perimeter += abs(complex(points[0] - points[-1]))
        elif n:
            perimeter += float(real_ranges[0] + real_ranges[-1])
        # Each beam's weight is half the gaps on either side of it (the trapezoid rule).
        weights = np.empty(n)
        if n:
            weights[0] = 0.0
            weights[1:] = gaps
            weights[:-1] += gaps
        if n > 1:
            weights[0] += wrap
            weights[-1] += wrap
        weights *= 0.25 / max(perimeter, _MIN_EDGE)
        self._ranges = np.ascontiguousarray(real_ranges, dtype=np.float64)
        self.real_sq = self._ranges * self._ranges
        self.weights = weights
        self._cap = cap
        self._bands: dict[float, FloatArray] = {}

    @classmethod
    def of_terms(
        cls,
        real_ranges: FloatArray,
        weights: FloatArray,
        cap: float | None = None,
        real_sq: FloatArray | None = None,
        band: FloatArray | None = None,
    ) -> PolarArea:
        """The area against ``real_ranges`` with per-beam ``weights`` computed already (by
        :func:`rlutf._kernels.scan_terms`, say), and if given, the squared ranges and the band
        of ``cap`` (:meth:`band`) too."""
        area = cls.__new__(cls)
        area._ranges = np.ascontiguousarray(real_ranges, dtype=np.float64)
        area.real_sq = area._ranges * area._ranges if real_sq is None else real_sq
        area.weights = weights
        area._cap = cap
        area._bands = {} if band is None or cap is None else {cap: band}
        return area

    def band(self, cap: float | None) -> FloatArray:
        """``(n,)`` the most each beam's ``|rho_v^2 - rho_r^2|`` counts, ``2 cap rho_r``; empty
        for no cap."""
        if cap is None:
            return _NO_CAP
        found = self._bands.get(cap)
        if found is None:
            found = (2.0 * cap) * self._ranges
            self._bands[cap] = found
        return found

    def __call__(self, virtual_ranges: FloatArray, cap: float | None = None) -> FloatArray:
        """``(K,)`` mean distances of ``(K, n)`` virtual ranges from the real ones, metres.

        ``cap`` replaces the cap given at construction."""
        diff = virtual_ranges * virtual_ranges
        diff -= self.real_sq
        np.abs(diff, out=diff)
        use = self._cap if cap is None else cap
        if use is not None:
            np.minimum(diff, self.band(use), out=diff)
        return np.asarray(diff.dot(self.weights), dtype=np.float64)


def polar_area(
    virtual_ranges: FloatArray,
    real_ranges: FloatArray,
    angles: FloatArray,
    closing: bool,
    cap: float | None = None,
) -> FloatArray:
    """Area between virtual and real scan polygons, over the real polygon's perimeter.

    Both polygons are star-shaped around the sensor and have their vertices on the same beams,
    so the area between them is ``integral |rho_v^2 - rho_r^2| / 2 dphi``, evaluated with the
    trapezoid rule between consecutive beams. This equals the area of the symmetric difference
    of the two sector fans and costs ``O(n)`` without polygon clipping. To score many virtual
    scans against one real scan, prepare :class:`PolarArea` once.

    Args:
        virtual_ranges: ``(K, n)`` ranges cast from ``K`` candidate poses, metres.
        real_ranges: ``(n,)`` measured ranges, metres.
        angles: ``(n,)`` beam angles in scan order, radians.
        closing: the polygons close through the sensor, so the sector between the last beam
            and the first is not part of them.
        cap: clip each beam's contribution at a band of this width, metres (see
            :class:`PolarArea`); ``None`` gives the exact area.

    Returns:
        ``(K,)`` mean distances between the boundaries, metres.
    """
    area = PolarArea(real_ranges, angles, closing, cap)
    return area(np.asarray(virtual_ranges, dtype=np.float64))
