"""A robot's recent odometry, and the ``map`` -> ``odom`` transform it gives with a pose.

REP 105: the odometry source owns ``odom`` -> base, so a localizer publishes
``map`` -> ``odom`` = (map -> base) composed with the inverse of (odom -> base) at the scan's
stamp, as AMCL does. The live front door and the rosbag2 writer both use this.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from rlutf.motion import compose, interpolate, inverse


class OdometryTrail:
    """Odometry poses by stamp, interpolated at any stamp (the nearest one outside the span).

    Args:
        kept: readings kept; the oldest half is dropped past it.
    """

    def __init__(self, kept: int = 512) -> None:
        self.kept = kept
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []

    def add(self, stamp_ns: int, pose: Sequence[float] | np.ndarray) -> None:
        """One reading ``(x, y, theta)`` in the odometry frame."""
        i = bisect.bisect_right(self._stamps, stamp_ns)
        self._stamps.insert(i, stamp_ns)
        self._poses.insert(i, np.asarray(pose, dtype=np.float64))
        if len(self._stamps) > self.kept:
            del self._stamps[: self.kept // 2], self._poses[: self.kept // 2]

    @property
    def stamps(self) -> Sequence[int]:
        """The readings' stamps, in order (the trail's own list: not to be changed)."""
        return self._stamps

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """The odometry pose at ``stamp_ns``; ``None`` with no reading."""
        s = self._stamps
        if not s:
            return None
        i = bisect.bisect_right(s, stamp_ns)
        if i == 0:
            return self._poses[0]
        if i == len(s) or s[i] == s[i - 1]:
            return self._poses[i - 1]
        frac = (stamp_ns - s[i - 1]) / (s[i] - s[i - 1])
        return interpolate(self._poses[i - 1], self._poses[i], frac)


def map_to_odom(map_base: Sequence[float] | np.ndarray, odom_base: np.ndarray) -> np.ndarray:
    """``map`` -> ``odom`` from the robot's pose in the map and its odometry pose."""
    return compose(np.asarray(map_base, dtype=np.float64), inverse(odom_base))
