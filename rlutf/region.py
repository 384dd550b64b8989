"""Exact ray casting from many poses near one reference pose, prepared once.

A localizer scores many candidate poses, all within a known distance of its prediction, against
one scan. :class:`RegionCaster` lists once every (wall, beam) pair that some pose of that region
may hit first, stores each pair's ray-segment intersection as linear forms in a few features of
a pose, and then casts from ``K`` poses with three small matrix products and a few element-wise
operations per call. The result equals brute-force intersection, like :func:`rlutf.cast_rays`.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.map import Map
from rlutf.raycast import Beams

FloatArray = NDArray[np.float64]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
#: Angular slack (radians) added to each wall's interval so that beams grazing an endpoint are
#: still tested exactly; extra candidates are rejected by the exact intersection test.
_ANGLE_SLACK = 1e-9
#: On maps with more walls than this, walls are taken ring by ring from the nearest and those
#: behind certain hits are skipped; the first ring's half-side, metres.
_RING_WALLS = 512
_FIRST_RING = 4.0
#: RegionCaster.cast works on chunks of at most this many (pose, pair) elements.
_CHUNK = 8192


class RegionCaster:
    """Exact ranges along one beam set from many poses near a reference pose, prepared once.

    A localizer scores many candidate poses, all within a known distance of its prediction,
    against one scan. This caster pays the per-wall and per-beam work once: it lists every
    (wall, beam) pair that can be hit first from *some* pose of the region (the wall's angular
    interval seen from the region centre, widened by the angle the region subtends at the wall
    and by the heading radius) and stores the ray-segment intersection of each pair as linear
    forms in a few features of a pose. Casting from ``K`` poses is then three small matrix
    products and a few element-wise operations, whatever the number of walls.

    Pairs that cannot be the first hit are left out, so that large maps stay cheap:

    * walls that the whole region sees from behind (a ray leaving the free space first crosses a
      wall from its free side, the walls' left, see :class:`Map`);
    * walls farther than a hit that is certain for every pose of the region: a beam well inside
      the interval of a wall that the whole region faces hits that wall from every pose, within
      a distance bound, and farther walls are skipped for that beam. On maps with many walls in
      range, walls are taken ring by ring outwards, so that far rings are not even listed; with
      one window of walls, the pairs are culled once listed (:meth:`_Region.cull`), which takes
      about 40 % of the pairs off every cast.

    Every pair kept is solved exactly, so for every pose of the region whose sensor lies in the
    free space the ranges equal brute-force intersection clamped to ``max_range``. Poses outside
    the region, or with the sensor outside the free space, get undefined ranges.

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
        x0, y0, t0 = _three_floats(centre)
        ox, oy, ot = _three_floats(sensor_offset)
        n = len(beams)
        self._origin = np.array([x0, y0])
        self._max_range = float(max_range)
        self._n = n
        self._targets: NDArray[np.intp] = np.empty(0, dtype=np.intp)
        base = complex(x0, y0)
        off = complex(ox, oy)
        shift = cmath.exp(1j * t0) * off  # sensor minus base position at the centre
        sensor = base + shift
        region = _Region(sensor, radius + abs(off) * heading_radius, heading_radius, t0 + ot, beams)
        far = max_range + region.reach
        rings = _ring_radii(len(world.segments), far)
        seen = np.zeros(len(world.segments), dtype=bool) if len(rings) > 1 else None
        # Per beam: no pose of the region has its first hit farther than this (rings only).
        bound = np.full(n, np.inf) if seen is not None else np.empty(0)
        found: list[tuple[NDArray[np.intp], NDArray[np.complex128], NDArray[np.complex128]]] = []
        near: list[FloatArray] = []
        self.poses_inside = False
        for ring, rho in enumerate(rings):
            walls = world.index.walls_near(sensor.real, sensor.imag, rho)
            if seen is not None:
                walls = walls[~seen[walls]]
                seen[walls] = True
            e = world.wall_direction[walls]
            a = world.wall_start[walls] - sensor
            w = a.conjugate() * e  # dot (real part) and cross (imaginary part) of a and e
            length = world.wall_length[walls]
            dist = _segment_distances(a, e, w.real, length)
            if ring == 0 and radius + abs(off) < rho:
                a_base = a + shift
                base_dist = (
                    dist
                    if off == 0
                    else _segment_distances(a_base, e, (a_base.conjugate() * e).real, length)
                )
                self.poses_inside = _region_inside(world, base, base_dist, radius)
            last = ring == len(rings) - 1
            beam, wall, certain = region.pairs(a, w, length, dist, None if ring == 0 else bound)
            if seen is None:
                beam, wall = region.cull(beam, wall, certain, a, e, dist)
            elif not last:
                region.tighten(bound, beam, wall, certain, w.imag / length, e)
            found.append((beam, e.take(wall), a.take(wall) + shift))
            if seen is not None:
                near.append(np.take(dist, wall) - region.reach)
            if not last and float(bound.max()) < rho - region.reach:
                break
        if len(found) == 1:
            beam, e, a = found[0]
        else:
            beam = np.concatenate([f[0] for f in found])
            e = np.concatenate([f[1] for f in found])
            a = np.concatenate([f[2] for f in found])
        if seen is not None:
            keep = np.concatenate(near) <= bound[beam] * (1.0 + 1e-9) + 1e-9
            beam, e, a = beam[keep], e[keep], a[keep]
        self._beam = beam
        self.pairs = total = len(beam)

        # Linear forms over the pose features f = (1, 0, x, y, cos t, sin t, m_r, m_i, 1, 0),
        # with (x, y) relative to the centre and m = conj(x + iy) exp(it); read as complex
        # numbers, f = (1, x + iy, exp(it), m, 1). For the ray c + t d and the wall a + s e of a
        # pair: tn = cross(a - c, e) = f[:6] . T, den = cross(d, e) = f[4:6] . Q[:2] and
        # sn = cross(a - c, d) = f[4:9] . Q[2:7]. A hit is den > 0, tn >= 0 and
        # 0 <= sn <= den, at t = tn / den. The coefficients come out of complex products as
        # (real, imaginary) pairs: T = (A, 0, ie, i conj(o) e) with A = cross(a, e), and
        # Q = (b e, -b a, b, Re(b o)) with b = -i conj(u) for the beam direction u.
        tn = np.empty((total, 3), dtype=np.complex128)
        tn[:, 0] = (a.conjugate() * e).imag
        np.multiply(e, 1j, out=tn[:, 1])
        np.multiply(e, off.conjugate() * 1j, out=tn[:, 2])
        self._tn = tn.view(np.float64)
        u = beams.unit if ot == 0 else beams.unit * cmath.exp(1j * ot)
        q = np.empty((total, 4), dtype=np.complex128)
        b = np.take(u.conjugate() * -1j, beam)
        np.multiply(b, e, out=q[:, 0])
        np.multiply(b, -a, out=q[:, 1])
        q[:, 2] = b
        q[:, 3] = 0.0 if off == 0 else (b * off).real
        self._q = q.view(np.float64)

    def cast(self, poses: FloatArray) -> FloatArray:
        """``(K, N)`` ranges, metres, from ``(K, 3)`` base poses of the region."""
        k_count = len(poses)
        if k_count == 0:
            return np.empty((0, self._n))
        f = np.empty((k_count, 10))
        fc = f.view(np.complex128)
        fc[:, ::4] = 1.0
        np.subtract(poses[:, :2], self._origin, out=f[:, 2:4])
        np.cos(poses[:, 2], out=f[:, 4])
        np.sin(poses[:, 2], out=f[:, 5])
        np.multiply(fc[:, 1].conjugate(), fc[:, 2], out=fc[:, 3])
        out = np.empty(k_count * self._n)
        out.fill(self._max_range)
        # Chunks keep every temporary small (large ones cost page faults on each call) and
        # every matrix product under the size at which BLAS starts threads.
        step = max(_CHUNK // k_count, 1)
        for lo in range(0, self.pairs, step):
            hi = min(lo + step, self.pairs)
            tn = f[:, :6] @ self._tn[lo:hi].T
            den = f[:, 4:6] @ self._q[lo:hi, :2].T
            sn = f[:, 4:9] @ self._q[lo:hi, 2:7].T
            low = den - sn
            np.minimum(low, sn, out=low)
            np.minimum(low, tn, out=low)
            miss = low < 0.0
            miss |= den <= 0.0
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.divide(tn, den, out=tn)
            np.putmask(t, miss, np.inf)
            target = self._target(k_count)
            if lo or hi < self.pairs:
                target = target.reshape(k_count, -1)[:, lo:hi]
            np.minimum.at(out, target.ravel(), t.ravel())
        return out.reshape(k_count, self._n)

    def _target(self, k_count: int) -> NDArray[np.intp]:
        """Flat output index of every (pose, pair) element, for ``k_count`` poses."""
        found = self._targets
        if len(found) < k_count * self.pairs:
            # Pose-major: the index for fewer poses is a prefix of this one.
            found = (self._beam + (np.arange(k_count) * self._n)[:, None]).ravel()
            self._targets = found
        return found[: k_count * self.pairs]


class _Region:
    """The poses of a :class:`RegionCaster` as seen from the walls: sensor positions within
    ``reach`` of ``sensor``, headings within ``heading_radius`` of ``heading``."""

    def __init__(
        self, sensor: complex, reach: float, heading_radius: float, heading: float, beams: Beams
    ) -> None:
        self.sensor = sensor
        self.reach = reach
        self.heading_radius = heading_radius
        self.heading = heading
        self.n = len(beams)
        # The sorted beams twice round the circle, so that every interval is one run.
        self.sorted_twice = np.concatenate([beams.sorted_wrapped, beams.sorted_wrapped + _TWO_PI])
        self.order_twice = np.concatenate([beams.order, beams.order])
        self._lo: FloatArray = np.empty(0)
        self._grow: FloatArray = np.empty(0)
        self._width: FloatArray = np.empty(0)
        self._position: NDArray[np.intp] = np.empty(0, dtype=np.intp)

    def pairs(
        self,
        a: NDArray[np.complex128],
        w: NDArray[np.complex128],
        length: FloatArray,
        dist: FloatArray,
        bound: FloatArray | None,
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """(beam, wall) of every pair that some pose of the region may hit first.

        Args:
            a: ``(m,)`` wall starts relative to the centre's sensor.
            w: ``(m,)`` ``conj(a) e``: dot and cross of start and direction.
            length: ``(m,)`` wall lengths.
            dist: ``(m,)`` distances from the centre's sensor to the walls.
            bound: per beam, the farthest first hit of any pose, or ``None``.

        Returns:
            Beam and wall index of each pair, and whether the wall is solid (the whole region
            on its free side, out of reach).
        """
        reach = self.reach
        cross = w.imag
        # Walls that the whole region sees from behind get no beams: they are never hit first.
        facing = cross > -reach * length
        aa = (a * a.conjugate()).real
        # The wall's interval seen from the centre, widened by the angle the region subtends at
        # the wall and by the heading radius; a wall within reach may be hit by any beam.
        span = np.arctan2(cross, aa + w.real)
        ratio = reach / np.maximum(dist, 1e-300)
        grow = np.arcsin(np.minimum(ratio, 1.0))
        grow += self.heading_radius + _ANGLE_SLACK
        width = np.abs(span)
        width += 2.0 * grow
        np.putmask(width, ratio >= 1.0, _TWO_PI)
        np.minimum(width, _TWO_PI, out=width)
        lo = np.arctan2(a.imag, a.real)
        lo += np.minimum(span, 0.0)
        lo -= grow + (self.heading + _PI)
        lo %= _TWO_PI
        lo -= _PI
        i0 = self.sorted_twice.searchsorted(lo, side="left")
        counts = self.sorted_twice.searchsorted(lo + width, side="right")
        counts -= i0
        np.maximum(counts, 0, out=counts)
        counts *= facing
        if bound is not None and len(counts):
            # Skip walls farther than the bound of every beam they could be hit by.
            runs = np.append(bound[self.order_twice], np.inf)
            ends = np.stack([i0, i0 + counts], axis=1).ravel()
            farthest = np.maximum.reduceat(runs, ends)[::2]
            counts[dist - reach > farthest * (1.0 + 1e-9) + 1e-9] = 0
        start = counts.cumsum()
        total = int(start[-1]) if len(start) else 0
        start -= counts
        i0 -= start
        position = i0.repeat(counts)
        position += np.arange(total)
        wall = np.arange(len(a)).repeat(counts)
        self._lo, self._grow, self._width, self._position = lo, grow, width, position
        solid = cross > reach * length
        solid &= ratio < 1.0
        return self.order_twice.take(position), wall, solid

    def cull(
        self,
        beam: NDArray[np.intp],
        wall: NDArray[np.intp],
        solid: NDArray[np.bool_],
        a: NDArray[np.complex128],
        e: NDArray[np.complex128],
        dist: FloatArray,
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """The pairs of the last :meth:`pairs` call less those behind a certain hit.

        On one window of walls this is what the rings do on large maps, with a cheaper bound:
        a pair is certain when the wall is solid and the beam lies inside the wall's interval
        by more than the widening (see :meth:`tighten`); every pose of the region then hits
        that wall along that beam, no farther than the wall's far end from the centre plus
        ``reach``. A pair whose wall is farther than that from every pose is never a first hit,
        and it is dropped: typically 40 % of the pairs, which cast() would solve for every pose.
        """
        lo, grow, width, position = self._lo, self._grow, self._width, self._position
        two_grow = 2.0 * grow
        inner_lo = self.sorted_twice.searchsorted(lo + two_grow, side="left")
        upper = lo + width
        upper -= two_grow
        inner_hi = self.sorted_twice.searchsorted(upper, side="right")
        inner_hi *= solid
        certain = position >= inner_lo.take(wall)
        certain &= position < inner_hi.take(wall)
        hits = certain.nonzero()[0]
        if not len(hits):
            return beam, wall
        far = np.abs(a + e)
        np.maximum(far, np.abs(a), out=far)
        far += self.reach
        bound = np.full(self.n, np.inf)
        np.minimum.at(bound, beam.take(hits), far.take(wall.take(hits)))
        bound *= 1.0 + 1e-9
        bound += 1e-9
        near = dist - self.reach
        keep = near.take(wall) <= bound.take(beam)
        return beam[keep], wall[keep]

    def tighten(
        self,
        bound: FloatArray,
        beam: NDArray[np.intp],
        wall: NDArray[np.intp],
        solid: NDArray[np.bool_],
        line: FloatArray,
        e: NDArray[np.complex128],
    ) -> None:
        """Lower ``bound`` with the pairs of the last :meth:`pairs` call that are certain hits.

        A pair is certain when the wall is solid and the beam lies inside the wall's interval by
        more than the widening: every pose of the region then hits the wall along that beam,
        at a point in the cone of directions ``beam +- grow`` from the centre, on the wall's line
        at distance ``line`` from the centre.
        """
        lo, grow, width, position = self._lo, self._grow, self._width, self._position
        inner_lo = self.sorted_twice.searchsorted(lo + 2.0 * grow, side="left")
        inner_hi = self.sorted_twice.searchsorted(lo + width - 2.0 * grow, side="right")
        inner_hi[~solid] = 0
        certain = position >= np.take(inner_lo, wall)
        certain &= position < np.take(inner_hi, wall)
        if not certain.any():
            return
        position, wall = position[certain], wall[certain]
        # Angle between the beam and the normal from the centre to the wall's line (the right
        # normal of the wall), plus the widening of the cone.
        normal = np.angle(e) - (_PI / 2.0 + self.heading)
        off_normal = np.take(self.sorted_twice, position) - np.take(normal, wall)
        off_normal += _PI
        off_normal %= _TWO_PI
        off_normal -= _PI
        np.abs(off_normal, out=off_normal)
        off_normal += np.take(grow, wall)
        ok = off_normal < _PI / 2.0 - 1e-6
        far = np.take(line, wall[ok]) / np.cos(off_normal[ok])
        far += self.reach
        far *= 1.0 + 1e-9
        far += 1e-9
        np.minimum.at(bound, np.take(self.order_twice, position[ok]), far)


def _ring_radii(walls: int, far: float) -> list[float]:
    """Radii of the square windows of walls taken in turn: one window unless many walls."""
    if walls <= _RING_WALLS:
        return [far]
    radii = []
    rho = _FIRST_RING
    while rho < far:
        radii.append(rho)
        rho *= 2.0
    radii.append(far)
    return radii


def _three_floats(values: ArrayLike) -> tuple[float, float, float]:
    x, y, t = np.asarray(values, dtype=np.float64).reshape(3).tolist()
    return x, y, t


def _segment_distances(
    a: NDArray[np.complex128], e: NDArray[np.complex128], dot: FloatArray, length: FloatArray
) -> FloatArray:
    """Distances from the origin to the segments ``a + s e``, ``0 <= s <= 1``.

    ``dot`` holds the dot products of ``a`` and ``e``, ``length`` the lengths of ``e``.
    """
    s = -dot / np.maximum(length * length, 1e-300)
    np.minimum(np.maximum(s, 0.0, out=s), 1.0, out=s)
    return np.asarray(np.abs(a + s * e), dtype=np.float64)


def _region_inside(world: Map, centre: complex, dist: FloatArray, radius: float) -> bool:
    """Whether the disc of ``radius`` around ``centre`` lies in the free space.

    ``dist`` holds the distances from the centre to every wall that could be within ``radius``.
    """
    if len(dist) and float(dist.min()) <= radius:
        return False
    return world.contains_point(centre.real, centre.imag)
