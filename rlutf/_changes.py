"""Compiled kernel of map health (see :mod:`rlutf.mapchange`): one scan counted into a grid."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rlutf.mapchange import TOP

#: Rows of the counts: marks of each kind, free passes, window masks and robot masks of each
#: kind; of the times: first and last stamp of each kind.
MARKS, FREE, WINDOWS, ROBOTS = 0, 2, 3, 5
FIRST, LAST = 0, 2


@njit(cache=True, nogil=True)
def observe(
    pose: np.ndarray, offset: np.ndarray, cos: np.ndarray, sin: np.ndarray,
    measured: np.ndarray, cast: np.ndarray, reals: np.ndarray, ints: np.ndarray,
    counts: np.ndarray, times: np.ndarray, stamp: int, window: int, robot: int,
) -> tuple[int, int]:  # fmt: skip
    """Count one scan of the robot base at ``pose`` (sensor at ``offset`` in the base frame).
    ``reals``: ``tolerance``, ``nudge``, the grid's origin ``(ox, oy)`` and ``cell``; ``ints``:
    ``stride`` and the grid's ``nx``, ``ny`` (the grid's constants, made once: every argument
    costs a conversion per call).

    Each return well short of the map's range marks its cell ``short`` (kind 0), each well
    beyond it marks the map wall's cell ``through`` (kind 1); every ``stride``-th beam counts
    the cells it crossed as ``free`` up to ``tolerance`` before where it ended. Sums (held at
    ``TOP``), ORs, min and max: any order, same grid. Returns the beams marked short and
    through."""
    tolerance, nudge, ox, oy, cell = reals[0], reals[1], reals[2], reals[3], reals[4]
    stride, nx, ny = ints[0], ints[1], ints[2]
    c0, s0 = math.cos(pose[2]), math.sin(pose[2])
    sx = pose[0] + c0 * offset[0] - s0 * offset[1]
    sy = pose[1] + s0 * offset[0] + c0 * offset[1]
    st = pose[2] + offset[2]
    n = measured.shape[0]
    cs, ss = math.cos(st), math.sin(st)
    marked = np.zeros(2, dtype=np.int64)
    for i in range(n):
        m, c = measured[i], cast[i]
        if not (math.isfinite(m) and math.isfinite(c)):
            continue
        dx = cs * cos[i] - ss * sin[i]
        dy = ss * cos[i] + cs * sin[i]
        if i % stride == 0:
            t = 0.5 * cell
            end = min(m, c) - tolerance
            while t < end:
                ix = int(math.floor((sx + t * dx - ox) / cell))
                iy = int(math.floor((sy + t * dy - oy) / cell))
                if 0 <= ix < nx and 0 <= iy < ny and counts[FREE, iy * nx + ix] < TOP:
                    counts[FREE, iy * nx + ix] += 1
                t += cell
        if m < c - tolerance:
            at = m
            kind = 0
        elif m > c + tolerance:
            at = c + nudge
            kind = 1
        else:
            continue
        ix = int(math.floor((sx + at * dx - ox) / cell))
        iy = int(math.floor((sy + at * dy - oy) / cell))
        if ix < 0 or ix >= nx or iy < 0 or iy >= ny:
            continue
        k = iy * nx + ix
        if counts[MARKS + kind, k] < TOP:
            counts[MARKS + kind, k] += 1
        counts[WINDOWS + kind, k] |= window
        counts[ROBOTS + kind, k] |= robot
        times[FIRST + kind, k] = min(times[FIRST + kind, k], stamp)
        times[LAST + kind, k] = max(times[LAST + kind, k], stamp)
        marked[kind] += 1
    return marked[0], marked[1]
