"""Point-to-line ICP against a polygon map or a cloud of points, initialised at the odometry
prediction.

The walls are sampled every ``spacing`` metres into points that carry their wall's unit normal
(pointing into the free space); a :class:`scipy.spatial.cKDTree` finds each scan point's
nearest wall sample. Each Gauss-Newton step minimises the Huber-weighted squared distances of
the scan points to those walls' lines, ``n . (R p + t - q)``, over ``(x, y, theta)``. Pairs
further apart than a gate are dropped (the gate shrinks from ``max_distance`` to
``min_distance`` over the iterations), and so are pairs whose wall faces away from the sensor
(the back side of a thin wall). Everything is vectorised over the scan's points.

Instead of a polygon map, ICP can run on the raw points of other scans (:func:`point_samples`:
the points thinned to one per ``spacing`` cell, each with the normal of a line fitted to its
neighbours, turned towards the sensor that saw it), as a scan matcher on a point map does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from bench.baselines.common import Estimate, FloatArray, scan_points
from rlutf.map import Map
from rlutf.motion import compose, wrap_scalar
from rlutf.scan import Scan


@dataclass(frozen=True)
class IcpConfig:
    """Parameters of :class:`PointToLineIcp`.

    Attributes:
        spacing: distance between wall samples, metres.
        max_iterations: most Gauss-Newton steps per scan.
        max_distance: correspondence gate of the first step, metres.
        min_distance: smallest gate, metres (reached by shrinking 30 % per step).
        huber: residual past which a pair's weight falls off as ``huber / |r|``, metres.
        tolerance: stop when a step moves less than this (metres, and radians), metres.
        min_pairs: fewer pairs than this leave the prediction unchanged, status ``lost``.
    """

    spacing: float = 0.02
    max_iterations: int = 20
    max_distance: float = 0.5
    min_distance: float = 0.1
    huber: float = 0.03
    tolerance: float = 1e-4
    min_pairs: int = 10


@dataclass(frozen=True, eq=False)
class WallSamples:
    """Points along a map's walls with their normals, and a k-d tree over them.

    Attributes:
        points: ``(K, 2)`` samples, metres.
        normals: ``(K, 2)`` unit normals of their walls, into the free space.
        walls: ``(K,)`` index of each sample's wall in the map's segments (non-decreasing), or
            of each point in the cloud it was thinned from (:func:`point_samples`).
        tree: the k-d tree over ``points``.
    """

    points: FloatArray
    normals: FloatArray
    walls: NDArray[np.int64]
    tree: cKDTree


@cache
def wall_samples(world: Map, spacing: float) -> WallSamples:
    """Sample every wall of ``world`` at most ``spacing`` metres apart (ends included)."""
    seg = world.segments
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    count = np.maximum(np.ceil(length / spacing).astype(np.int64), 1) + 1
    wall = np.repeat(np.arange(len(seg)), count)
    first = np.cumsum(count) - count
    frac = (np.arange(int(count.sum())) - np.repeat(first, count)) / np.repeat(count - 1, count)
    points = seg[wall, :2] + frac[:, None] * d[wall]
    # Walls run with the free space on their left: the left normal points into it.
    normals = np.column_stack([-d[:, 1], d[:, 0]]) / length[:, None]
    return WallSamples(points, normals[wall], wall, cKDTree(points))


def point_samples(
    points: FloatArray, sensors: FloatArray, spacing: float = 0.02, radius: float = 0.1
) -> WallSamples:
    """Raw scan points as ICP's map: one point per ``spacing`` cell, with normals.

    Args:
        points: ``(n, 2)`` scan end points in the map frame, metres.
        sensors: ``(n, 2)`` where the sensor was that saw each point.
        spacing: cell side of the thinning, metres (the first point of each cell is kept).
        radius: neighbours within this fit each point's line, metres; a point with fewer than
            three gets the direction to its sensor as its normal.

    Returns:
        The kept points, their unit normals (turned towards their sensors) and a k-d tree;
        ``walls`` holds each kept point's index in ``points``.
    """
    key = np.floor(np.asarray(points) / spacing).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    first.sort()
    pts, seen = points[first], sensors[first]
    tree = cKDTree(pts)
    dist, idx = tree.query(pts, k=16, distance_upper_bound=radius)
    near = np.isfinite(dist)
    nb = pts[np.where(near, idx, 0)]
    count = near.sum(axis=1)
    mean = (nb * near[..., None]).sum(axis=1) / count[:, None]
    c = (nb - mean[:, None, :]) * near[..., None]
    cxx, cyy = (c[..., 0] ** 2).sum(axis=1), (c[..., 1] ** 2).sum(axis=1)
    cxy = (c[..., 0] * c[..., 1]).sum(axis=1)
    axis = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # the line's direction
    normals = np.column_stack([-np.sin(axis), np.cos(axis)])
    to_sensor = seen - pts
    lonely = count < 3
    normals[lonely] = to_sensor[lonely] / np.hypot(*to_sensor[lonely].T)[:, None]
    flip = np.einsum("ij,ij->i", normals, to_sensor) < 0.0
    normals[flip] *= -1.0
    return WallSamples(pts, normals, first.astype(np.int64), tree)


class PointToLineIcp:
    """Tracks a robot by point-to-line ICP of each scan against the map.

    Args:
        world: the map.
        pose: ``(3,)`` initial pose.
        config: parameters.
        samples: the points to match against instead of ``world``'s walls (e.g.
            :func:`point_samples` of other scans); ``world`` is then not used.
    """

    def __init__(
        self,
        world: Map | None,
        pose: FloatArray,
        config: IcpConfig | None = None,
        samples: WallSamples | None = None,
    ) -> None:
        self.config = config or IcpConfig()
        if samples is None:
            if world is None:
                raise ValueError("PointToLineIcp: needs a map (world) or samples, got neither")
            samples = wall_samples(world, self.config.spacing)
        self._walls = samples
        self._pose = np.asarray(pose, dtype=np.float64).copy()

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Predict with ``motion``, then align ``scan`` to the map."""
        cfg = self.config
        pose = compose(self._pose, motion)
        valid = scan.valid()
        local = scan_points(scan.ranges[valid], scan.angles[valid], scan.sensor_offset)
        offset = scan.sensor_offset
        gate = cfg.max_distance
        status = "lost"
        for _ in range(cfg.max_iterations):
            c, s = math.cos(pose[2]), math.sin(pose[2])
            rotated = local @ np.array([[c, s], [-s, c]])
            world_pts = rotated + pose[:2]
            dist, idx = self._walls.tree.query(world_pts, distance_upper_bound=gate)
            found = np.isfinite(dist)
            idx = np.where(found, idx, 0)
            q = self._walls.points[idx]
            n = self._walls.normals[idx]
            sensor = pose[:2] + np.array(
                [c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]]
            )
            facing = np.einsum("ij,ij->i", n, sensor - q) > 0.0
            keep = found & facing
            if int(keep.sum()) < cfg.min_pairs:
                status = "lost"
                break
            n, q, rot, w_pts = n[keep], q[keep], rotated[keep], world_pts[keep]
            r = np.einsum("ij,ij->i", n, w_pts - q)
            jac = np.column_stack([n, n[:, 1] * rot[:, 0] - n[:, 0] * rot[:, 1]])
            weight = np.minimum(1.0, cfg.huber / np.maximum(np.abs(r), 1e-12))
            h = jac.T @ (jac * weight[:, None])
            g = jac.T @ (weight * r)
            try:
                step = -np.linalg.solve(h, g)
            except np.linalg.LinAlgError:
                status = "lost"
                break
            pose = pose + step
            status = "corrected"
            gate = max(cfg.min_distance, gate * 0.7)
            if math.hypot(step[0], step[1]) < cfg.tolerance and abs(step[2]) < cfg.tolerance:
                break
        self._pose = np.array([pose[0], pose[1], wrap_scalar(float(pose[2]))])
        return Estimate(self._pose.copy(), status)
