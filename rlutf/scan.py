"""Laser scans as arrays, and the scan polygon the localizer compares.

A :class:`Scan` holds one 2D laser scan with the meaning of ROS ``sensor_msgs/LaserScan``: beam
``i`` points at ``angle_min + i * angle_increment`` in the sensor frame; a range that is NaN,
below ``range_min`` or above ``range_max`` is *no return*.

Rule for beams without a return: they are left out. The scan polygon joins the neighbouring
returns directly, and the virtual scan is masked the same way, so both polygons are built from
the same beams. When the returns do not go all the way round (a field of view under 360
degrees, or a gap wider than ``max_gap`` around the sensor), the polygon closes through the
sensor origin, as the region a scanner sees is bounded by its first and last beams.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from rlutf.errors import GeometryError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, eq=False)
class Scan:
    """One laser scan.

    Attributes:
        ranges: ``(N,)`` ranges in metres; NaN where the sensor reported nothing.
        angle_min: angle of beam 0 in the sensor frame, radians.
        angle_increment: angle between beams, radians (may be negative).
        range_min: shorter ranges are no return, metres.
        range_max: longer ranges are no return, metres.
        sensor_offset: ``(3,)`` pose of the sensor in the robot base frame.
    """

    ranges: FloatArray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    sensor_offset: FloatArray

    @classmethod
    def create(
        cls,
        ranges: ArrayLike,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
        sensor_offset: ArrayLike = (0.0, 0.0, 0.0),
    ) -> Scan:
        """Build a scan; ``None`` entries in ``ranges`` become NaN.

        Raises:
            GeometryError: non-finite geometry, zero increment or an empty range interval.
        """
        r = np.array(
            [np.nan if v is None else v for v in ranges] if isinstance(ranges, list) else ranges,
            dtype=np.float64,
        ).reshape(-1)
        off = np.array(sensor_offset, dtype=np.float64).reshape(3)
        values = (angle_min, angle_increment, range_min, range_max)
        if not all(math.isfinite(v) for v in values) or not np.isfinite(off).all():
            raise GeometryError("scan geometry must be finite")
        if angle_increment == 0.0:
            raise GeometryError("angle_increment must not be zero")
        if not 0.0 <= range_min < range_max:
            raise GeometryError(f"need 0 <= range_min < range_max, got {range_min}, {range_max}")
        r.flags.writeable = False
        off.flags.writeable = False
        return cls(
            r, float(angle_min), float(angle_increment), float(range_min), float(range_max), off
        )

    @property
    def angles(self) -> FloatArray:
        """``(N,)`` beam angles in the sensor frame, radians."""
        return self.angle_min + self.angle_increment * np.arange(len(self.ranges), dtype=np.float64)

    def valid(self) -> BoolArray:
        """``(N,)`` mask of beams with a return."""
        r = self.ranges
        # NaN and infinities fail one of the comparisons (which do not warn).
        valid = r >= self.range_min
        valid &= r <= self.range_max
        return valid

    def covers_full_circle(self) -> bool:
        """Whether the beams go all the way round (the last beam ends where the first starts)."""
        return abs(self.angle_increment) * len(self.ranges) >= _TWO_PI - 1e-6


def beam_points(
    ranges: FloatArray, cos_a: FloatArray, sin_a: FloatArray, sensor_offset: FloatArray
) -> FloatArray:
    """End points of beams in the robot frame.

    Args:
        ranges: ``(..., N)`` ranges, metres.
        cos_a: ``(N,)`` cosines of the beam angles in the sensor frame.
        sin_a: ``(N,)`` sines of the beam angles.
        sensor_offset: ``(3,)`` sensor pose in the robot frame.

    Returns:
        ``(..., N, 2)`` points in the robot frame.
    """
    sx, sy, st = float(sensor_offset[0]), float(sensor_offset[1]), float(sensor_offset[2])
    lx = ranges * cos_a
    ly = ranges * sin_a
    if st == 0.0:
        return np.asarray(np.stack([lx + sx, ly + sy], axis=-1), dtype=np.float64)
    c, s = math.cos(st), math.sin(st)
    return np.asarray(
        np.stack([sx + c * lx - s * ly, sy + s * lx + c * ly], axis=-1), dtype=np.float64
    )


def needs_origin(
    angles: FloatArray, full_circle: bool, max_gap: float, gaps: FloatArray | None = None
) -> bool:
    """Whether a scan polygon over beams at ``angles`` must close through the sensor.

    Args:
        angles: ``(n,)`` angles of the beams kept, in scan order, radians.
        full_circle: the scanner sweeps 360 degrees.
        max_gap: widest angular gap between consecutive kept beams that is still bridged by a
            polygon edge, radians.
        gaps: ``|diff(angles)|`` if already at hand.
    """
    if len(angles) < 2:
        return True
    if gaps is None:
        gaps = np.abs(np.diff(angles))
    if float(gaps.max()) > max_gap:
        return True
    if not full_circle:
        return True
    closing = _TWO_PI - abs(float(angles[-1] - angles[0]))
    return closing > max_gap


def simplify_ring(points: FloatArray, tolerance: float) -> FloatArray:
    """Douglas-Peucker simplification of a closed ring, keeping its first vertex.

    Range noise otherwise turns into turning-function noise: a wall seen through 1 cm of noise
    becomes a zig-zag of large turns. Simplifying at the noise level restores straight walls.

    Args:
        points: ``(n, 2)`` ring vertices without the closing repeat.
        tolerance: largest distance of a removed vertex from the simplified ring, metres.

    Returns:
        ``(m, 2)`` vertices, ``m <= n``, the first vertex unchanged.
    """
    if tolerance <= 0.0 or len(points) < 4:
        return points
    closed = np.vstack([points, points[:1]])
    line = shapely.linestrings(closed)
    out = shapely.get_coordinates(shapely.simplify(line, tolerance, preserve_topology=False))
    return np.asarray(out[:-1], dtype=np.float64)
