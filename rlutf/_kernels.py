"""Compiled ray casting and the polar-area comparison.

Plain loops over contiguous float64 and int64 arrays, compiled by numba (``cache=True``: the
machine code is kept beside this file, or in ``NUMBA_CACHE_DIR``, so a service does not compile
again at each start). No ``fastmath``: the kernels evaluate in a fixed order, so results are bit
for bit the same on every run of a given version. The public wrappers live in
:mod:`rlutf.raycast`, :mod:`rlutf.refine`, :mod:`rlutf.field` and :mod:`rlutf.relocalize`;
they validate inputs, these do not.

The walls are indexed by the map's uniform grid (:class:`rlutf.map.WallIndex`): a ray walks the
grid cells it crosses in order (Amanatides and Woo, 1987) and tests only the walls listed in
them, so a cast costs the cells crossed times the walls per cell, whatever the size of the map.

A *grid* below is the tuple ``(segments, x0, y0, cell, nx, ny, cell_start, cell_walls)``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_INF = math.inf


@njit(cache=True, nogil=True)
def cast_ray(
    px: float,
    py: float,
    dx: float,
    dy: float,
    max_range: float,
    front_only: bool,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
) -> tuple[float, int]:
    """First hit of the ray ``p + t d`` (``d`` a unit vector) with a wall, ``t <= max_range``.

    With ``front_only``, walls met from behind are skipped: from a point of the free space the
    first wall a ray meets is always met from its free side, so a caster that starts in the
    free space loses nothing and tests half the walls.

    Returns ``(t, wall)``; ``(inf, -1)`` when nothing is hit within ``max_range``.
    """
    gx1 = x0 + nx * cell
    gy1 = y0 + ny * cell
    t_in = 0.0
    t_out = max_range
    # Clip the ray to the grid's box (slabs).
    if dx != 0.0:
        ta = (x0 - px) / dx
        tb = (gx1 - px) / dx
        if ta > tb:
            ta, tb = tb, ta
        t_in = max(t_in, ta)
        t_out = min(t_out, tb)
    elif px < x0 or px > gx1:
        return _INF, -1
    if dy != 0.0:
        ta = (y0 - py) / dy
        tb = (gy1 - py) / dy
        if ta > tb:
            ta, tb = tb, ta
        t_in = max(t_in, ta)
        t_out = min(t_out, tb)
    elif py < y0 or py > gy1:
        return _INF, -1
    if t_in > t_out:
        return _INF, -1
    cx = int(math.floor((px + t_in * dx - x0) / cell))
    cy = int(math.floor((py + t_in * dy - y0) / cell))
    cx = min(max(cx, 0), nx - 1)
    cy = min(max(cy, 0), ny - 1)
    if dx > 0.0:
        step_x, next_x, delta_x = 1, (x0 + (cx + 1) * cell - px) / dx, cell / dx
    elif dx < 0.0:
        step_x, next_x, delta_x = -1, (x0 + cx * cell - px) / dx, -cell / dx
    else:
        step_x, next_x, delta_x = 0, _INF, _INF
    if dy > 0.0:
        step_y, next_y, delta_y = 1, (y0 + (cy + 1) * cell - py) / dy, cell / dy
    elif dy < 0.0:
        step_y, next_y, delta_y = -1, (y0 + cy * cell - py) / dy, -cell / dy
    else:
        step_y, next_y, delta_y = 0, _INF, _INF
    best = _INF
    best_wall = -1
    while True:
        c = cy * nx + cx
        for k in range(cell_start[c], cell_start[c + 1]):
            w = cell_walls[k]
            ax = segments[w, 0]
            ay = segments[w, 1]
            ex = segments[w, 2] - ax
            ey = segments[w, 3] - ay
            # den > 0: the ray meets the wall from its free side (the walls' left).
            den = dx * ey - dy * ex
            qx = ax - px
            qy = ay - py
            tn = qx * ey - qy * ex
            sn = qx * dy - qy * dx
            if den < 0.0:
                if front_only:
                    continue
                den = -den
                tn = -tn
                sn = -sn
            elif den == 0.0:
                continue
            # Hit iff t = tn / den >= 0 and 0 <= s = sn / den <= 1; divide only for a new best.
            if tn < 0.0 or sn < 0.0 or sn > den or tn >= best * den:
                continue
            best = tn / den
            best_wall = w
        exit_t = min(next_x, next_y)
        # A hit inside this cell is nearer than anything in the cells after it.
        if best <= exit_t or exit_t > t_out:
            break
        if next_x < next_y:
            cx += step_x
            next_x += delta_x
            if cx < 0 or cx >= nx:
                break
        else:
            cy += step_y
            next_y += delta_y
            if cy < 0 or cy >= ny:
                break
    if best > max_range:
        return _INF, -1
    return best, best_wall


@njit(cache=True, nogil=True)
def cast_fan(
    sx: float,
    sy: float,
    st: float,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    max_range: float,
    front_only: bool,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
    ranges: np.ndarray,
    walls: np.ndarray,
) -> None:
    """Cast beams at angles ``a`` (given as cosines and sines) from the sensor pose ``(sx, sy,
    st)`` into ``ranges`` and ``walls`` (``inf`` and ``-1`` for no hit)."""
    c = math.cos(st)
    s = math.sin(st)
    for i in range(len(cos_a)):
        dx = c * cos_a[i] - s * sin_a[i]
        dy = s * cos_a[i] + c * sin_a[i]
        t, w = cast_ray(
            sx, sy, dx, dy, max_range, front_only, segments, x0, y0, cell, nx, ny, cell_start,
            cell_walls,
        )  # fmt: skip
        ranges[i] = t
        walls[i] = w


@njit(cache=True, nogil=True)
def cast_poses(
    poses: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    max_range: float,
    front_only: bool,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(K, N)`` ranges and hit walls of ``N`` beams from ``(K, 3)`` sensor poses."""
    k_count = poses.shape[0]
    n = len(cos_a)
    ranges = np.empty((k_count, n))
    walls = np.empty((k_count, n), dtype=np.int64)
    for k in range(k_count):
        cast_fan(
            poses[k, 0],
            poses[k, 1],
            poses[k, 2],
            cos_a,
            sin_a,
            max_range,
            front_only,
            segments,
            x0,
            y0,
            cell,
            nx,
            ny,
            cell_start,
            cell_walls,
            ranges[k],
            walls[k],
        )
    return ranges, walls


@njit(cache=True, nogil=True)
def _sensor_pose(x: float, y: float, t: float, off: np.ndarray) -> tuple[float, float, float]:
    c = math.cos(t)
    s = math.sin(t)
    return x + c * off[0] - s * off[1], y + s * off[0] + c * off[1], t + off[2]


@njit(cache=True, nogil=True)
def score_area(
    poses: np.ndarray,
    off: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    real_sq: np.ndarray,
    weights: np.ndarray,
    cap: np.ndarray,
    range_limit: float,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
) -> np.ndarray:
    """Polar-area discrepancy (see :class:`rlutf.discrepancy.PolarArea`) of ``(K, 3)`` base
    poses: ``sum_i weights_i min(|rho_i^2 - real_sq_i|, cap_i)``, a beam with no hit within
    ``range_limit`` counting as ``range_limit``; ``cap`` empty for no cap."""
    k_count = poses.shape[0]
    n = len(cos_a)
    out = np.empty(k_count)
    capped = len(cap) == n
    for k in range(k_count):
        sx, sy, st = _sensor_pose(poses[k, 0], poses[k, 1], poses[k, 2], off)
        c = math.cos(st)
        s = math.sin(st)
        total = 0.0
        for i in range(n):
            dx = c * cos_a[i] - s * sin_a[i]
            dy = s * cos_a[i] + c * sin_a[i]
            t, _ = cast_ray(
                sx, sy, dx, dy, range_limit, True, segments, x0, y0, cell, nx, ny, cell_start,
                cell_walls,
            )  # fmt: skip
            t = min(t, range_limit)
            diff = abs(t * t - real_sq[i])
            if capped and diff > cap[i]:
                diff = cap[i]
            total += weights[i] * diff
        out[k] = total
    return out


@njit(cache=True, nogil=True)
def area_of_ranges(
    ranges: np.ndarray, weights: np.ndarray, real_sq: np.ndarray, band: np.ndarray, limit: float
) -> float:
    """``sum_i weights_i min(|min(rho_i, limit)^2 - real_sq_i|, band_i)`` (``band`` empty: no
    cap): the polar area of one virtual scan, as :func:`score_area` scores it."""
    capped = len(band) == len(ranges)
    total = 0.0
    for i in range(len(ranges)):
        t = ranges[i]
        if not t <= limit:  # inf and NaN too
            t = limit
        diff = abs(t * t - real_sq[i])
        if capped and diff > band[i]:
            diff = band[i]
        total += weights[i] * diff
    return total


@njit(cache=True, nogil=True)
def scan_terms(
    ranges: np.ndarray,
    angles: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    range_min: float,
    range_max: float,
    full_circle: bool,
    max_gap: float,
    cap: float,
) -> tuple[int, bool, np.ndarray, float]:
    """What one scan's comparison needs, in one pass: the beams with a return, whether the
    polygons close through the sensor (:func:`rlutf.scan.needs_origin`), and each kept beam's
    polar-area weight (:class:`rlutf.discrepancy.PolarArea`, trapezoid rule over the real
    polygon's perimeter); and the kept beams gathered (one call, not a dozen array operations
    in Python per scan): their angles, cosines, sines, ranges, squared ranges, the capped
    area's band ``2 cap rho_r`` (not filled for ``cap <= 0``) and the longest kept range (0 if
    none). Returns ``(kept beams n, closing, terms, longest)``, ``terms`` the ``(7, n)`` rows
    weights, angles, cosines, sines, ranges, squared ranges and band: one array, as each array
    returned costs the call about 0.4 us to hand to Python."""
    n_all = len(ranges)
    keep = np.empty(n_all, dtype=np.int64)
    n = 0
    for i in range(n_all):
        r = ranges[i]
        if r >= range_min and r <= range_max:  # NaN fails both
            keep[n] = i
            n += 1
    terms = np.empty((7, n))
    weights = terms[0]
    weights[:] = 0.0
    k_angles = terms[1]
    k_cos = terms[2]
    k_sin = terms[3]
    k_ranges = terms[4]
    k_sq = terms[5]
    band = terms[6]
    two_cap = 2.0 * cap
    longest = 0.0
    for k in range(n):
        i = keep[k]
        r = ranges[i]
        k_angles[k] = angles[i]
        k_cos[k] = cos_a[i]
        k_sin[k] = sin_a[i]
        k_ranges[k] = r
        k_sq[k] = r * r
        if cap > 0.0:
            band[k] = two_cap * r
        longest = max(longest, r)
    if n == 0:
        return n, True, terms, longest
    widest = 0.0
    perimeter = 0.0
    for k in range(n - 1):
        i, j = keep[k], keep[k + 1]
        gap = abs(angles[j] - angles[i])
        widest = max(widest, gap)
        weights[k + 1] += gap
        weights[k] += gap
        dx = ranges[j] * cos_a[j] - ranges[i] * cos_a[i]
        dy = ranges[j] * sin_a[j] - ranges[i] * sin_a[i]
        perimeter += math.hypot(dx, dy)
    first, last = keep[0], keep[n - 1]
    closing = True
    if n >= 2 and widest <= max_gap and full_circle:
        closing = 2.0 * math.pi - abs(angles[last] - angles[first]) > max_gap
    if not closing and n > 1:
        wrap = 2.0 * math.pi - abs(angles[last] - angles[first])
        weights[0] += wrap
        weights[n - 1] += wrap
        dx = ranges[first] * cos_a[first] - ranges[last] * cos_a[last]
        dy = ranges[first] * sin_a[first] - ranges[last] * sin_a[last]
        perimeter += math.hypot(dx, dy)
    else:
        perimeter += ranges[first] + ranges[last]
    scale = 0.25 / max(perimeter, 1e-9)
    for k in range(n):
        weights[k] *= scale
    return n, closing, terms, longest
