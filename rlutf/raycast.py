"""Exact, vectorised ray casting against a polygon map.

Only the walls in index cells within ``max_range`` of the poses are considered, and each wall is
tested only against the beams inside the angular interval it subtends as seen from each pose
(found by binary search over the sorted beam angles). The cost of a call therefore grows with
the number of walls near the robot times the beams each one covers, not with the size of the
map. Every candidate (beam, wall) pair is then solved exactly, so the result equals brute-force
segment intersection. All poses of a call are processed in one vectorised pass, which is what
makes evaluating a handful of candidate poses cheap; :class:`Beams` holds what depends only on
the beam angles so that repeated calls with one scan's beams do not recompute it.

:func:`cast_rays` works for any poses; :class:`rlutf.region.RegionCaster` is for many calls from
poses near one reference pose (a localizer's candidates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.map import Map

FloatArray = NDArray[np.float64]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
#: Angular slack (radians) added to each wall's interval so that beams grazing an endpoint are
#: still tested exactly; extra candidates are rejected by the exact intersection test.
_ANGLE_SLACK = 1e-9


@dataclass(frozen=True, eq=False)
class Beams:
    """Beam directions prepared for :func:`cast_rays`.

    Attributes:
        angles: ``(N,)`` beam angles, radians, relative to the ray origin's heading.
        cos: ``(N,)`` cosines of ``angles``.
        sin: ``(N,)`` sines of ``angles``.
        unit: ``(N,)`` beam directions as complex numbers ``cos + i sin``.
        order: indices that sort the angles wrapped to ``[-pi, pi)``.
        sorted_wrapped: the wrapped angles in that order.
    """

    angles: FloatArray
    cos: FloatArray
    sin: FloatArray
    unit: NDArray[np.complex128]
    order: NDArray[np.intp]
    sorted_wrapped: FloatArray

    @classmethod
    def of(cls, angles: ArrayLike) -> Beams:
        """Prepare beams from ``(N,)`` angles in radians."""
        a = np.array(angles, dtype=np.float64).reshape(-1)
        wrapped = (a + _PI) % _TWO_PI - _PI
        order = np.argsort(wrapped, kind="stable")
        cos, sin = np.cos(a), np.sin(a)
        return cls(a, cos, sin, cos + 1j * sin, order, wrapped[order])

    def __len__(self) -> int:
        return len(self.angles)

    def select(self, mask: NDArray[np.bool_]) -> Beams:
        """The beams where ``(N,)`` ``mask`` is true, in their order, without sorting again."""
        keep = np.asarray(mask, dtype=bool)
        index = keep.nonzero()[0]
        if len(index) == len(keep):
            return self
        in_sorted = keep[self.order]
        # New index of each kept beam (the others are never read).
        renumber = np.empty(len(keep), dtype=np.intp)
        renumber[index] = np.arange(len(index))
        return Beams(
            self.angles[index],
            self.cos[index],
            self.sin[index],
            self.unit[index],
            renumber[self.order[in_sorted]],
            self.sorted_wrapped[in_sorted],
        )


def cast_rays(
    world: Map, poses: ArrayLike, angles: ArrayLike | Beams, max_range: float
) -> FloatArray:
    """Ranges from each pose along each beam to the nearest wall.

    Args:
        world: the map.
        poses: ``(K, 3)`` ray origins and headings ``(x, y, theta)`` in the map frame (or one
            ``(3,)`` pose).
        angles: ``(N,)`` beam angles in radians relative to each pose's heading, or
            :class:`Beams` prepared from them.
        max_range: hits farther than this (metres) count as no hit.

    Returns:
        ``(K, N)`` ranges in metres; ``inf`` where a beam hits no wall within ``max_range``.
    """
    beams = angles if isinstance(angles, Beams) else Beams.of(angles)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    k_count, n = len(p), len(beams)
    out = np.full(k_count * n, np.inf)
    if n == 0 or k_count == 0 or not max_range > 0:
        return out.reshape(k_count, n)
    # One wall set for all poses: those near the poses' bounding box.
    xs, ys = p[:, 0], p[:, 1]
    x0, x1, y0, y1 = float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())
    spread = 0.5 * max(x1 - x0, y1 - y0)
    walls = world.index.walls_near(0.5 * (x0 + x1), 0.5 * (y0 + y1), max_range + spread)
    m = len(walls)
    if m == 0:
        return out.reshape(k_count, n)
    # Walls in each pose's own frame as complex numbers, flattened to K * M rows: start point
    # q and direction e. Complex arithmetic keeps the number of numpy calls (the real cost at
    # these sizes) low.
    rot = np.exp(-1j * p[:, 2])[:, None]
    q = ((world.wall_start[walls] - (xs + 1j * ys)[:, None]) * rot).ravel()
    e = (world.wall_direction[walls] * rot).ravel()
    qe = q + e

    # Angular interval [lo, hi] of each wall; hi may pass +pi, and then wraps to -pi.
    a0 = np.angle(q)
    span = np.angle(qe * q.conjugate())
    lo = a0 + np.minimum(span, 0.0) - _ANGLE_SLACK
    lo[lo < -_PI] += _TWO_PI
    hi = lo + np.abs(span) + 2.0 * _ANGLE_SLACK
    sorted_rel = beams.sorted_wrapped
    i0 = sorted_rel.searchsorted(lo, side="left")
    c1 = sorted_rel.searchsorted(hi, side="right") - i0
    c2 = sorted_rel.searchsorted(hi - _TWO_PI, side="right")
    counts = np.concatenate([c1, c2])
    total = int(counts.sum())
    if total == 0:
        return out.reshape(k_count, n)
    rows = np.arange(len(counts)).repeat(counts)
    first = np.concatenate([i0, np.zeros_like(c2)]) - (np.cumsum(counts) - counts)
    beam = beams.order[np.arange(total) + first[rows]]
    wall = rows % len(q)

    # Exact ray-segment intersection in the pose frame: t * d = q + s * e, with
    # cross(a, b) = Im(conj(a) * b).
    d = beams.unit[beam]
    wq = q[wall]
    we = e[wall]
    wqc = wq.conjugate()
    denom = (d.conjugate() * we).imag
    t_num = (wqc * we).imag
    s_num = (wqc * d).imag
    # Hit iff 0 <= s <= 1 and 0 <= t <= max_range, tested without dividing by zero.
    sign = np.sign(denom)
    t_num *= sign
    s_num *= sign
    adenom = np.abs(denom)
    hit = (adenom > 0.0) & (s_num >= 0.0) & (s_num <= adenom) & (t_num >= 0.0)
    hit &= t_num <= max_range * adenom
    t = t_num[hit] / adenom[hit]
    flat = (wall[hit] // m) * n + beam[hit]
    np.minimum.at(out, flat, t)
    return out.reshape(k_count, n)
