"""Exact, vectorised ray casting against a polygon map.

Only the walls in index cells within ``max_range`` of the poses are considered, and each wall is
tested only against the beams inside the angular interval it subtends as seen from each pose
(found by binary search over the sorted beam angles). The cost of a call therefore grows with
the number of walls near the robot times the beams each one covers, not with the size of the
map. Every candidate (beam, wall) pair is then solved exactly, so the result equals brute-force
segment intersection. All poses of a call are processed in one vectorised pass, which is what
makes evaluating a handful of candidate poses cheap; :class:`Beams` holds what depends only on
the beam angles so that repeated calls with one scan's beams do not recompute it.
"""

from __future__ import annotations

import cmath
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
        if keep.all():
            return self
        in_sorted = keep[self.order]
        renumber = np.cumsum(keep) - 1
        return Beams(
            self.angles[keep],
            self.cos[keep],
            self.sin[keep],
            self.unit[keep],
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


class RegionCaster:
    """Exact ranges along one beam set from many poses near a reference pose, prepared once.

    A localizer scores many candidate poses, all within a known distance of its prediction,
    against one scan. This caster pays the per-wall and per-beam work once: it lists every
    (wall, beam) pair that can be hit from *some* pose of the region (the wall's angular interval
    seen from the region centre, widened by the angle the region subtends at the wall and by the
    heading radius) and stores the ray-segment intersection of each pair as linear forms in seven
    features of a pose. Casting from ``K`` poses is then three small matrix products and a few
    element-wise operations, whatever the number of walls.

    Only hits on a wall's free side count, and walls the whole region sees from behind are
    skipped: a ray leaving a point of the free space first crosses a wall from its free side (the
    walls' left, see :class:`Map`). Every pair kept is solved exactly, so for every pose of the
    region whose sensor lies in the free space the ranges equal brute-force intersection clamped
    to ``max_range``. Poses outside the region, or with the sensor outside the free space, get
    undefined ranges.

    Args:
        world: the map.
        beams: beam directions in the sensor frame.
        centre: ``(3,)`` reference pose ``(x, y, theta)`` of the robot base, map frame.
        radius: the poses cast from lie within this distance of the centre, metres.
        heading_radius: and their headings within this angle of the centre's, radians.
        max_range: metres; a beam with no hit within it gets ``max_range``.
        sensor_offset: ``(3,)`` sensor pose in the base frame: rays start at
            ``pose (+) sensor_offset``.

    Attributes:
        poses_inside: every base position of the region lies in the free space, so callers need
            not test candidates with :meth:`Map.contains`.
        pairs: (wall, beam) pairs solved per pose.
    """

    def __init__(
        self,
        world: Map,
        beams: Beams,
        centre: ArrayLike,
        radius: float,
        heading_radius: float,
        max_range: float,
        sensor_offset: ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        x0, y0, t0 = (float(v) for v in np.asarray(centre, dtype=np.float64).reshape(3))
        ox, oy, ot = (float(v) for v in np.asarray(sensor_offset, dtype=np.float64).reshape(3))
        n = len(beams)
        self._origin = np.array([x0, y0])
        self._max_range = float(max_range)
        off = complex(ox, oy)
        base = complex(x0, y0)
        sensor = base + cmath.exp(1j * t0) * off
        # Sensor positions of the region lie within `reach` of the centre's sensor position.
        reach = radius + abs(off) * heading_radius
        walls = world.index.walls_near(sensor.real, sensor.imag, max_range + reach)
        a = world.wall_start[walls] - base
        e = world.wall_direction[walls]
        a_s = a - (sensor - base)
        dist = _segment_distances(a_s, e)
        base_dist = dist if off == 0 else _segment_distances(a, e)
        self.poses_inside = _region_inside(world, base, base_dist, radius)
        facing = (a_s.conjugate() * e).imag > -reach * np.abs(e)
        a, e, a_s, dist = a[facing], e[facing], a_s[facing], dist[facing]
        m = len(a)

        # Beams each wall can be hit by from some pose of the region: a superset.
        span = np.angle((a_s + e) * a_s.conjugate())
        ratio = reach / np.maximum(dist, 1e-300)
        grow = np.arcsin(np.minimum(ratio, 1.0))
        grow += heading_radius + _ANGLE_SLACK
        width = np.abs(span)
        width += 2.0 * grow
        width[ratio >= 1.0] = _TWO_PI
        lo = np.angle(a_s) + np.minimum(span, 0.0)
        lo -= grow + (t0 + ot + _PI)
        lo %= _TWO_PI
        lo -= _PI
        hi = lo + np.minimum(width, _TWO_PI)
        sorted_rel = beams.sorted_wrapped
        i0 = sorted_rel.searchsorted(lo, side="left")
        counts = np.concatenate(
            [
                sorted_rel.searchsorted(hi, side="right") - i0,
                sorted_rel.searchsorted(hi - _TWO_PI, side="right"),
            ]
        )
        total = int(counts.sum())
        rows = np.arange(2 * m).repeat(counts)
        i0.resize(2 * m, refcheck=False)  # the wrapped parts start at sorted beam 0
        first = i0 - (np.cumsum(counts) - counts)
        beam = beams.order[np.arange(total) + first[rows]]
        wall = rows % max(m, 1)
        # Group the pairs by beam. A beam no wall can reach gets a stand-in pair with a wall of
        # zero length, which never hits: the beam's range becomes max_range.
        per_beam = np.bincount(beam, minlength=n)
        empty = np.flatnonzero(per_beam == 0)
        if len(empty):
            beam = np.concatenate([beam, empty])
            wall = np.concatenate([wall, np.full(len(empty), m)])
            per_beam[empty] = 1
            a = np.append(a, 0.0)
            e = np.append(e, 0.0)
        by_beam = np.argsort(beam, kind="stable")
        beam, wall = beam[by_beam], wall[by_beam]
        self._starts = np.cumsum(per_beam) - per_beam
        self.pairs = total

        # Linear forms over the pose features f = (x, y, 1, cos t, sin t, m_r, m_i), with (x, y)
        # relative to the centre and m = conj(x + iy) exp(it). Per pair, with the ray
        # c + t d and the wall a + s e: tn = cross(a - c, e), den = cross(d, e) and
        # sn = cross(a - c, d); a hit is den > 0, tn >= 0 and 0 <= sn <= den, at t = tn / den.
        u = beams.unit * cmath.exp(1j * ot)
        k = off.conjugate() * e
        wall_forms = np.stack([-e.imag, e.real, (a.conjugate() * e).imag, -k.imag, k.real])
        self._tn = wall_forms[:, wall]
        g = u[beam].conjugate() * e[wall]
        self._den = np.stack([g.imag, -g.real])
        h = a[wall].conjugate() * u[beam]
        beam_forms = np.stack([-(off.conjugate() * u).imag, -u.imag, -u.real])[:, beam]
        self._sn = np.stack([beam_forms[0], h.imag, h.real, beam_forms[1], beam_forms[2]])

    def cast(self, poses: FloatArray) -> FloatArray:
        """``(K, N)`` ranges, metres, from ``(K, 3)`` base poses of the region."""
        f = np.empty((len(poses), 7))
        np.subtract(poses[:, :2], self._origin, out=f[:, :2])
        f[:, 2] = 1.0
        np.cos(poses[:, 2], out=f[:, 3])
        np.sin(poses[:, 2], out=f[:, 4])
        f[:, 5:] = f[:, 0:1] * f[:, 3:5]
        f[:, 5:] += f[:, 1:2] * f[:, 4:2:-1] * (1.0, -1.0)
        tn = f[:, :5] @ self._tn
        den = f[:, 3:5] @ self._den
        sn = f[:, 2:] @ self._sn
        low = den - sn
        np.minimum(low, sn, out=low)
        np.minimum(low, tn, out=low)
        hit = low >= 0.0
        hit &= den > 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(hit, tn / den, np.inf)
        out = np.minimum.reduceat(t, self._starts, axis=1)
        return np.asarray(np.minimum(out, self._max_range, out=out), dtype=np.float64)


def _segment_distances(a: NDArray[np.complex128], e: NDArray[np.complex128]) -> FloatArray:
    """Distances from the origin to the segments ``a + s e``, ``0 <= s <= 1``."""
    ee = e.real * e.real + e.imag * e.imag
    s = -(a.conjugate() * e).real / np.maximum(ee, 1e-300)
    np.clip(s, 0.0, 1.0, out=s)
    return np.asarray(np.abs(a + s * e), dtype=np.float64)


def _region_inside(world: Map, centre: complex, dist: FloatArray, radius: float) -> bool:
    """Whether the disc of ``radius`` around ``centre`` lies in the free space.

    ``dist`` holds the distances from the centre to every wall that could be within ``radius``.
    """
    if len(dist) and float(dist.min()) <= radius:
        return False
    return bool(world.contains(np.array([[centre.real, centre.imag]]))[0])
