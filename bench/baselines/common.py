"""Types the baselines share: an estimate per scan, and scan end points."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Estimate(NamedTuple):
    """A method's answer to one scan.

    Attributes:
        pose: ``(3,)`` the pose ``(x, y, theta)`` in the map frame, or ``None`` if the method
            gave none.
        status: ``tracking``, ``corrected``, ``lost``, or ``predicted`` (a method that did not
            use the scan, e.g. AMCL between filter updates).
        covariance: ``(3, 3)`` covariance of ``(x, y, theta)`` (m^2, m rad, rad^2), if the
            method gives one.
    """

    pose: FloatArray | None
    status: str
    covariance: FloatArray | None = None


def scan_points(ranges: FloatArray, angles: FloatArray, sensor_offset: FloatArray) -> FloatArray:
    """``(n, 2)`` end points of beams in the robot frame.

    Args:
        ranges: ``(n,)`` ranges with a return, metres.
        angles: ``(n,)`` their angles in the sensor frame, radians.
        sensor_offset: ``(3,)`` sensor pose in the robot frame.
    """
    a = angles + sensor_offset[2]
    return np.column_stack(
        [sensor_offset[0] + ranges * np.cos(a), sensor_offset[1] + ranges * np.sin(a)]
    )
