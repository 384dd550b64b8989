"""The Cramer-Rao bound of a scan against a map (Censi, ICRA 2007).

With independent Gaussian range noise of standard deviation ``sigma``, the Fisher information
of a scan about the pose ``p = (x, y, theta)`` is ``I = sum_i J_i^T J_i / sigma^2`` where
``J_i = d r_i / d p`` is the derivative of beam ``i``'s range with respect to the pose. For a
beam leaving the sensor at ``s`` in direction ``v`` and hitting a wall with unit normal ``n``
at range ``r``, the exact ray geometry gives (Censi's eq. for a polygonal environment)::

    d r / d s     = -n / (n . v)
    d r / d phi   = -r (n . v_perp) / (n . v)      (phi: the beam's heading)

and the chain rule through the sensor's mounting offset gives ``J_i``. Any unbiased estimator
from that one scan has ``E|xy error|^2 >= trace((I^-1)_xy)``; the bound reported per scan is
``sqrt(trace((I^-1)_xy))``, in metres.

Beams without a return, beams whose measured range is shorter than the map's by more than
``outlier_sigmas`` (a person in the way: it says nothing about the map), and beams more
oblique than :data:`MAX_INCIDENCE` (where the model of a thin ray fails and the derivatives
blow up) are left out. A scan whose information matrix is singular (a featureless corridor)
has an infinite bound.
"""

from __future__ import annotations

import math

import numpy as np

from bench.baselines.icp import wall_samples
from bench.scenarios import FloatArray
from rlutf.map import Map
from rlutf.motion import compose
from rlutf.raycast import cast_rays
from rlutf.scan import Scan

#: Beams hitting a wall more obliquely than this (radians from the normal) are left out.
MAX_INCIDENCE = math.radians(80.0)
#: Nearest wall samples whose walls are candidates for a hit point.
_CANDIDATES = 4


def hit_walls(world: Map, points: FloatArray) -> FloatArray:
    """``(n, 2)`` unit normals of the walls that ``(n, 2)`` hit points lie on.

    Candidates are the walls of the :data:`_CANDIDATES` nearest wall samples (a k-d tree over
    points 2 cm apart); of those, the wall at the smallest exact distance wins.
    """
    samples = wall_samples(world, 0.02)
    wall_of = samples.walls
    _, idx = samples.tree.query(points, k=_CANDIDATES)
    cand = wall_of[idx]
    seg = world.segments[cand]
    a = seg[..., :2]
    d = seg[..., 2:] - a
    rel = points[:, None, :] - a
    length2 = np.maximum(np.einsum("pkj,pkj->pk", d, d), 1e-18)
    t = np.clip(np.einsum("pkj,pkj->pk", rel, d) / length2, 0.0, 1.0)
    off = rel - t[..., None] * d
    pick = np.argmin(np.einsum("pkj,pkj->pk", off, off), axis=1)
    best = cand[np.arange(len(points)), pick]
    d_best = world.segments[best, 2:] - world.segments[best, :2]
    normal = np.column_stack([-d_best[:, 1], d_best[:, 0]])
    return np.asarray(normal / np.hypot(normal[:, 0], normal[:, 1])[:, None], dtype=np.float64)


def range_jacobian(
    world: Map, pose: FloatArray, angles: FloatArray, sensor_offset: FloatArray, max_range: float
) -> tuple[FloatArray, FloatArray]:
    """Ranges of beams cast from ``pose`` and their derivatives with respect to the pose.

    Args:
        world: the map.
        pose: ``(3,)`` robot pose.
        angles: ``(N,)`` beam angles in the sensor frame, radians.
        sensor_offset: ``(3,)`` sensor pose in the robot frame.
        max_range: metres.

    Returns:
        ``(N,)`` ranges (``inf`` past ``max_range``) and ``(N, 3)`` derivatives ``d r / d
        (x, y, theta)``; rows of beams with no hit or past :data:`MAX_INCIDENCE` are NaN.
    """
    sensor = compose(pose, sensor_offset)
    r = np.asarray(cast_rays(world, sensor[None], angles, max_range)[0], dtype=np.float64)
    jac = np.full((len(angles), 3), math.nan)
    hit = np.isfinite(r) & (r <= max_range)
    if not hit.any():
        return r, jac
    phi = sensor[2] + angles[hit]
    v = np.column_stack([np.cos(phi), np.sin(phi)])
    n = hit_walls(world, sensor[:2] + r[hit, None] * v)
    cos_inc = np.einsum("ij,ij->i", n, v)
    ok = np.abs(cos_inc) >= math.cos(MAX_INCIDENCE)
    v_perp = np.column_stack([-v[:, 1], v[:, 0]])
    safe = np.where(ok, cos_inc, 1.0)
    dr_ds = -n / safe[:, None]
    dr_dphi = -r[hit] * np.einsum("ij,ij->i", n, v_perp) / safe
    # Sensor position s = (x, y) + R(theta) o: ds/dtheta = R'(theta) o.
    c, s = math.cos(pose[2]), math.sin(pose[2])
    ox, oy = float(sensor_offset[0]), float(sensor_offset[1])
    ds_dtheta = np.array([-s * ox - c * oy, c * ox - s * oy])
    rows = np.column_stack([dr_ds, dr_ds @ ds_dtheta + dr_dphi])
    rows[~ok] = math.nan
    jac[hit] = rows
    return r, jac


def fisher_information(jacobian: FloatArray, sigma: float) -> FloatArray:
    """``(3, 3)`` Fisher information of independent ranges with derivatives ``(N, 3)``."""
    j = jacobian[np.isfinite(jacobian).all(axis=1)]
    return np.asarray(j.T @ j / (sigma * sigma), dtype=np.float64)


def position_bound(information: FloatArray) -> float:
    """``sqrt(trace((I^-1)_xy))``, metres; ``inf`` for a singular information matrix."""
    scale = float(np.max(np.abs(np.diag(information)))) if information.size else 0.0
    if scale <= 0.0 or np.linalg.cond(information) > 1e12:
        return math.inf
    cov = np.linalg.inv(information)
    return math.sqrt(max(float(cov[0, 0] + cov[1, 1]), 0.0))


def scan_bound(
    world: Map, pose: FloatArray, scan: Scan, sigma: float, outlier_sigmas: float = 3.0
) -> float:
    """The position bound of one scan taken at the true ``pose``.

    Args:
        world: the map.
        pose: ``(3,)`` true pose of the robot base.
        scan: the scan (its no-return mask and outliers are respected).
        sigma: range noise, one sigma, metres.
        outlier_sigmas: beams shorter than the map's range by more than this many sigmas
            are left out.
    """
    valid = scan.valid()
    angles = scan.angles[valid]
    r, jac = range_jacobian(world, pose, angles, scan.sensor_offset, scan.range_max)
    measured = scan.ranges[valid]
    jac[measured < r - outlier_sigmas * sigma] = math.nan
    return position_bound(fisher_information(jac, sigma))


def run_bounds(world: Map, truth: FloatArray, scans: tuple[Scan, ...], sigma: float) -> FloatArray:
    """``(U,)`` per-update bounds of scans ``1..`` at their true poses."""
    return np.array([scan_bound(world, truth[k], scans[k], sigma) for k in range(1, len(scans))])
