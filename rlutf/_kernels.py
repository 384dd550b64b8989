"""Compiled kernels of the hot paths: ray casting, scan scoring, refinement, distance fields.

Plain loops over contiguous float64 and int64 arrays, compiled by numba (``cache=True``: the
machine code is kept beside this file, or in ``NUMBA_CACHE_DIR``, so a service does not compile
again at each start). No ``fastmath``: the kernels evaluate in a fixed order, so results are bit
for bit the same on every run of a given version. The public wrappers live in
:mod:`rlutf.raycast`, :mod:`rlutf.refine` and :mod:`rlutf.field`; they validate inputs, these
do not.

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
#: Residual that a beam with no virtual hit counts as in the refinement's cost, metres.
_MISS = 1.0


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
def _median_abs(values: np.ndarray, count: int) -> float:
    if count == 0:
        return 0.0
    return float(np.median(np.abs(values[:count])))


@njit(cache=True, nogil=True)
def _linearise(
    x: float,
    y: float,
    t: float,
    off: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    real: np.ndarray,
    max_range: float,
    min_cos_incidence: float,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
    ranges: np.ndarray,
    residual: np.ndarray,
    jac: np.ndarray,
    used: np.ndarray,
) -> int:
    """Cast from the base pose ``(x, y, t)``; fill each beam's virtual range, residual
    ``real - virtual``, range Jacobian and whether it is used. Returns the beams used.

    For a beam at world angle ``phi`` (direction ``v``, ``v_perp`` its left normal) hitting a
    wall with unit normal ``n`` at range ``rho`` from the sensor ``s``, ``d rho / d s = -n /
    (n . v)`` and ``d rho / d phi = -rho (n . v_perp) / (n . v)`` (Censi 2007); the sensor
    moves with the base through its mounting offset. Beams with no hit, or hitting a wall more
    obliquely than ``min_cos_incidence`` (where a thin ray is a poor model), are not used.
    """
    c = math.cos(t)
    s = math.sin(t)
    sx = x + c * off[0] - s * off[1]
    sy = y + s * off[0] + c * off[1]
    # d(sensor position) / d theta of the base.
    dsx = -s * off[0] - c * off[1]
    dsy = c * off[0] - s * off[1]
    st = t + off[2]
    cs = math.cos(st)
    ss = math.sin(st)
    count = 0
    for i in range(len(cos_a)):
        vx = cs * cos_a[i] - ss * sin_a[i]
        vy = ss * cos_a[i] + cs * sin_a[i]
        rho, w = cast_ray(
            sx, sy, vx, vy, max_range, True, segments, x0, y0, cell, nx, ny, cell_start,
            cell_walls,
        )  # fmt: skip
        ranges[i] = rho
        used[i] = False
        if w < 0:
            residual[i] = math.nan
            continue
        residual[i] = real[i] - rho
        ex = segments[w, 2] - segments[w, 0]
        ey = segments[w, 3] - segments[w, 1]
        length = math.hypot(ex, ey)
        n_x = -ey / length
        n_y = ex / length
        ndv = n_x * vx + n_y * vy
        if abs(ndv) < min_cos_incidence:
            continue
        gx = -n_x / ndv
        gy = -n_y / ndv
        g_phi = -rho * (n_x * -vy + n_y * vx) / ndv
        jac[i, 0] = gx
        jac[i, 1] = gy
        jac[i, 2] = gx * dsx + gy * dsy + g_phi
        used[i] = True
        count += 1
    return count


@njit(cache=True, nogil=True)
def _normal_equations(
    residual: np.ndarray, jac: np.ndarray, used: np.ndarray, scale: float, h: np.ndarray,
    g: np.ndarray,
) -> None:  # fmt: skip
    """Cauchy-weighted ``h = J^T W J`` and ``g = J^T W r`` over the beams used."""
    h[:, :] = 0.0
    g[:] = 0.0
    inv = 1.0 / (scale * scale)
    for i in range(len(residual)):
        if not used[i]:
            continue
        r = residual[i]
        w = 1.0 / (1.0 + r * r * inv)
        for a in range(3):
            wa = w * jac[i, a]
            g[a] += wa * r
            for b in range(a, 3):
                h[a, b] += wa * jac[i, b]
    for a in range(3):
        for b in range(a):
            h[a, b] = h[b, a]


@njit(cache=True, nogil=True)
def _cost(residual: np.ndarray, scale: float) -> float:
    """Robust cost ``sum c^2 / 2 log(1 + (r / c)^2)`` over every beam; a beam whose virtual ray
    hits nothing counts as off by :data:`_MISS` (so losing a beam never makes a pose cheaper)."""
    inv = 1.0 / (scale * scale)
    cost = 0.0
    for i in range(len(residual)):
        r = residual[i]
        if not math.isfinite(r):
            r = _MISS
        cost += math.log1p(r * r * inv)
    return 0.5 * scale * scale * cost


@njit(cache=True, nogil=True)
def _inverse3(a: np.ndarray, out: np.ndarray) -> bool:
    """Inverse of the symmetric positive 3x3 matrix ``a`` (adjugate over determinant) into
    ``out``; False if it is singular."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    scale = abs(a[0, 0]) * abs(a[1, 1]) * abs(a[2, 2])
    if not det > 1e-14 * scale or not math.isfinite(det):
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) * inv
    out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * inv
    out[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * inv
    out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) * inv
    out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * inv
    out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * inv
    # Symmetric by construction up to rounding: make it exactly so.
    for r in range(3):
        for c in range(r):
            m = 0.5 * (out[r, c] + out[c, r])
            out[r, c] = m
            out[c, r] = m
    return True


@njit(cache=True, nogil=True)
def refine(
    pose: np.ndarray,
    off: np.ndarray,
    cos_a: np.ndarray,
    sin_a: np.ndarray,
    real: np.ndarray,
    max_range: float,
    min_cos_incidence: float,
    scale_min: float,
    scale_max: float,
    prior: np.ndarray,
    max_iterations: int,
    tolerance: float,
    fit_distance: float,
    area_weights: np.ndarray,
    area_real_sq: np.ndarray,
    area_band: np.ndarray,
    area_limit: float,
    accept_below: float,
    segments: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    nx: int,
    ny: int,
    cell_start: np.ndarray,
    cell_walls: np.ndarray,
    out_pose: np.ndarray,
    out_ranges: np.ndarray,
    out_residual: np.ndarray,
    out_covariance: np.ndarray,
) -> tuple[int, float, int, int, bool, float, float, bool]:
    """Levenberg-Marquardt on the ranges, re-casting every beam at every step.

    Minimises ``sum_i rho_c(real_i - virtual_i(pose)) + sigma^2 / 2 (p - p0)^T prior (p - p0)``
    with the Cauchy kernel ``rho_c(r) = c^2 / 2 log(1 + (r / c)^2)``. The scale follows the
    residuals, ``c = 2.3849 sigma`` with ``sigma = 1.4826 median |r|`` clamped to ``[scale_min,
    scale_max] / 2.3849`` (95 % efficiency on Gaussian noise; beams off by much more than the
    noise, people and map errors, weigh almost nothing). The small ``prior`` (information per
    unit variance, diagonal ``(3,)``) holds directions the scan does not constrain (a corridor's
    axis) at the start pose. Stops when a step is under ``tolerance`` (metres and radians), after
    ``max_iterations`` casts, or when no step lowers the cost.

    Writes the final pose, its virtual ranges and residuals, and its covariance ``sigma^2 (J^T J +
    sigma^2 prior)^-1`` over the inlier beams (``|r| <= 3 sigma``). Returns ``(casts, sigma,
    beams used, beams within fit_distance, whether the covariance exists, the polar area of the
    start pose, that of the final pose, gated)``.

    With ``area_weights`` (empty: none), the polar area (:func:`area_of_ranges`) of the start
    pose and of the final pose come from the casts the refinement makes anyway; and with
    ``accept_below > 0``, a start pose whose area is not under it is *gated*: the refinement
    stops after its first cast (the caller searches first: Algorithm 1's acceptance test).
    """
    n = len(cos_a)
    ranges = np.empty(n)
    residual = np.empty(n)
    jac = np.zeros((n, 3))
    used = np.zeros(n, dtype=np.bool_)
    t_ranges = np.empty(n)
    t_residual = np.empty(n)
    t_jac = np.zeros((n, 3))
    t_used = np.zeros(n, dtype=np.bool_)
    h = np.empty((3, 3))
    g = np.empty(3)
    a = np.empty((3, 3))
    b = np.empty(3)
    step = np.empty(3)
    inverse = np.empty((3, 3))
    scratch = np.empty(n)
    p0x, p0y, p0t = pose[0], pose[1], pose[2]
    x, y, t = p0x, p0y, p0t
    count = _linearise(
        x, y, t, off, cos_a, sin_a, real, max_range, min_cos_incidence, segments,
        x0, y0, cell, nx, ny, cell_start, cell_walls, ranges, residual, jac, used,
    )  # fmt: skip
    casts = 1
    lam = 1e-4
    has_area = len(area_weights) == n
    d_start = area_of_ranges(ranges, area_weights, area_real_sq, area_band, area_limit) if (
        has_area
    ) else math.nan  # fmt: skip
    gated = accept_below > 0.0 and not d_start < accept_below
    k = 0
    for i in range(n):
        if used[i]:
            scratch[k] = residual[i]
            k += 1
    sigma = 1.4826 * _median_abs(scratch, k)
    scale = min(max(2.3849 * sigma, scale_min), scale_max)
    while casts < max_iterations and count >= 3 and not gated:
        _normal_equations(residual, jac, used, scale, h, g)
        cost = _cost(residual, scale)
        var = (scale / 2.3849) ** 2
        dx0, dy0, dt0 = x - p0x, y - p0y, t - p0t
        cost += 0.5 * var * (prior[0] * dx0 * dx0 + prior[1] * dy0 * dy0 + prior[2] * dt0 * dt0)
        g[0] -= var * prior[0] * dx0
        g[1] -= var * prior[1] * dy0
        g[2] -= var * prior[2] * dt0
        accepted = False
        converged = False
        while casts < max_iterations:
            for r in range(3):
                for c in range(3):
                    a[r, c] = h[r, c]
                a[r, r] = h[r, r] * (1.0 + lam) + var * prior[r]
                b[r] = g[r]
            if not _inverse3(a, inverse):
                lam *= 10.0
                if lam > 1e8:
                    break
                continue
            for r in range(3):
                step[r] = inverse[r, 0] * b[0] + inverse[r, 1] * b[1] + inverse[r, 2] * b[2]
            if math.hypot(step[0], step[1]) < tolerance and abs(step[2]) < tolerance:
                # At the bottom: a step this small is not worth a cast.
                converged = True
                break
            nx_, ny_, nt_ = x + step[0], y + step[1], t + step[2]
            t_count = _linearise(
                nx_, ny_, nt_, off, cos_a, sin_a, real, max_range, min_cos_incidence, segments,
                x0, y0, cell, nx, ny, cell_start, cell_walls, t_ranges, t_residual, t_jac, t_used,
            )  # fmt: skip
            casts += 1
            d0, d1, d2 = nx_ - p0x, ny_ - p0y, nt_ - p0t
            new_cost = _cost(t_residual, scale) + 0.5 * var * (
                prior[0] * d0 * d0 + prior[1] * d1 * d1 + prior[2] * d2 * d2
            )
            if new_cost <= cost:
                x, y, t = nx_, ny_, nt_
                ranges, t_ranges = t_ranges, ranges
                residual, t_residual = t_residual, residual
                jac, t_jac = t_jac, jac
                used, t_used = t_used, used
                count = t_count
                lam = max(lam * 0.1, 1e-7)
                accepted = True
                break
            lam *= 10.0
            if lam > 1e8:
                break
        if not accepted or converged:
            break
        k = 0
        for i in range(n):
            if used[i]:
                scratch[k] = residual[i]
                k += 1
        sigma = 1.4826 * _median_abs(scratch, k)
        scale = min(max(2.3849 * sigma, scale_min), scale_max)
    out_pose[0] = x
    out_pose[1] = y
    out_pose[2] = t
    for i in range(n):
        out_ranges[i] = ranges[i]
        out_residual[i] = residual[i]
    sigma = max(sigma, scale_min / 2.3849)
    fitted = 0
    for i in range(n):
        if abs(residual[i]) <= fit_distance:  # NaN (no hit) never fits
            fitted += 1
    # Information of the inlier beams per unit variance, plus the prior.
    h[:, :] = 0.0
    limit = 3.0 * sigma
    for i in range(n):
        if used[i] and abs(residual[i]) <= limit:
            for r in range(3):
                for c in range(3):
                    h[r, c] += jac[i, r] * jac[i, c]
    for r in range(3):
        h[r, r] += sigma * sigma * prior[r]
    ok = count >= 3 and _inverse3(h, out_covariance)
    if ok:
        out_covariance *= sigma * sigma
    d_final = d_start
    if has_area and casts > 1:
        d_final = area_of_ranges(ranges, area_weights, area_real_sq, area_band, area_limit)
    return casts, sigma, count, fitted, ok, d_start, d_final, gated


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
def distance_field(
    segments: np.ndarray, fx0: float, fy0: float, resolution: float, width: int, height: int,
    truncation: float,
) -> np.ndarray:  # fmt: skip
    """``(height, width)`` distances from cell centres to the nearest wall, truncated."""
    field = np.full((height, width), truncation, dtype=np.float32)
    for w in range(segments.shape[0]):
        ax = segments[w, 0]
        ay = segments[w, 1]
        ex = segments[w, 2] - ax
        ey = segments[w, 3] - ay
        ee = ex * ex + ey * ey
        c0 = max(int(math.floor((min(ax, ax + ex) - truncation - fx0) / resolution)), 0)
        c1 = min(int(math.floor((max(ax, ax + ex) + truncation - fx0) / resolution)), width - 1)
        r0 = max(int(math.floor((min(ay, ay + ey) - truncation - fy0) / resolution)), 0)
        r1 = min(int(math.floor((max(ay, ay + ey) + truncation - fy0) / resolution)), height - 1)
        for r in range(r0, r1 + 1):
            py = fy0 + (r + 0.5) * resolution - ay
            for c in range(c0, c1 + 1):
                px = fx0 + (c + 0.5) * resolution - ax
                s = (px * ex + py * ey) / ee if ee > 0.0 else 0.0
                s = min(max(s, 0.0), 1.0)
                d = math.hypot(px - s * ex, py - s * ey)
                field[r, c] = min(field[r, c], d)
    return field


@njit(cache=True, nogil=True)
def score_field_grid(
    cx: float,
    cy: float,
    ct: float,
    offsets_xy: np.ndarray,
    headings: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    field: np.ndarray,
    fx0: float,
    fy0: float,
    resolution: float,
    cap: float,
) -> np.ndarray:
    """Mean capped squared distance field at the scan's points for every pose of a grid.

    The poses are ``(cx, cy) + offsets_xy[j]`` with heading ``ct + headings[h]``; the scan's
    points are ``(px, py)`` in the base frame. Points off the field count as ``cap``. Returns
    ``(H, J)`` scores (metres squared)."""
    height, width = field.shape
    n = len(px)
    out = np.empty((len(headings), offsets_xy.shape[0]))
    wx = np.empty(n)
    wy = np.empty(n)
    cap2 = cap * cap
    inv = 1.0 / resolution
    for h in range(len(headings)):
        c = math.cos(ct + headings[h])
        s = math.sin(ct + headings[h])
        for i in range(n):
            wx[i] = (c * px[i] - s * py[i] + cx - fx0) * inv
            wy[i] = (s * px[i] + c * py[i] + cy - fy0) * inv
        for j in range(offsets_xy.shape[0]):
            ox = offsets_xy[j, 0] * inv
            oy = offsets_xy[j, 1] * inv
            total = 0.0
            for i in range(n):
                col = int(math.floor(wx[i] + ox))
                row = int(math.floor(wy[i] + oy))
                if 0 <= col < width and 0 <= row < height:
                    d = float(field[row, col])
                    total += min(d * d, cap2)
                else:
                    total += cap2
            out[h, j] = total / n
    return out


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
) -> tuple[np.ndarray, bool, np.ndarray]:
    """What one scan's comparison needs, in one pass: the beams with a return, whether the
    polygons close through the sensor (:func:`rlutf.scan.needs_origin`), and each kept beam's
    polar-area weight (:class:`rlutf.discrepancy.PolarArea`, trapezoid rule over the real
    polygon's perimeter). Returns ``(kept indices, closing, weights)``."""
    n_all = len(ranges)
    keep = np.empty(n_all, dtype=np.int64)
    n = 0
    for i in range(n_all):
        r = ranges[i]
        if r >= range_min and r <= range_max:  # NaN fails both
            keep[n] = i
            n += 1
    keep = keep[:n]
    weights = np.zeros(n)
    if n == 0:
        return keep, True, weights
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
    return keep, closing, weights
