"""Compiled Levenberg-Marquardt on the ranges of a scan (see :mod:`rlutf.refine`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from rlutf._kernels import area_of_ranges, cast_ray

#: Residual that a beam with no virtual hit counts as in the refinement's cost, metres.
_MISS = 1.0


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
    heading_tolerance: float,
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
    axis) at the start pose. Stops after ``max_iterations`` casts, when no step lowers the cost,
    or on a step shorter than ``tolerance`` (metres) that turns less than ``heading_tolerance``
    (radians): that last step is taken without a cast (most refinements save one or two casts
    so; the step's error is of second order in its length).

    Writes the final pose, its virtual ranges and residuals, and its covariance ``sigma^2 (J^T J +
    sigma^2 prior)^-1`` over the inlier beams (``|r| <= 3 sigma``); after a last step taken
    without a cast, the ranges, residuals and covariance are those of the cast before it, at
    most ``tolerance`` away. Returns ``(casts, sigma,
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
            if math.hypot(step[0], step[1]) < tolerance and abs(step[2]) < heading_tolerance:
                # Near the bottom: a step this small is taken as the linearisation gives it,
                # without a cast to check it (its error is of second order in the step).
                x, y, t = x + step[0], y + step[1], t + step[2]
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
