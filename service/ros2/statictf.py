"""Where a robot's laser is: its ``tf_static`` tree, from the base frame to the scan's frame.

Nav2 robots publish the fixed links (``base_footprint`` -> ``base_link`` -> ``base_scan``) on
``tf_static`` once, transient local; AMCL looks the laser's pose up in that tree. The wire
contract's LaserScan carries it as ``sensor_offset`` (x, y and yaw in the base frame), so each
scan's offset is the chain of static transforms from the base frame to the scan's
``header.frame_id``. A level laser is assumed: roll and pitch are dropped.
"""

from __future__ import annotations

import threading

import numpy as np

from rlutf.motion import compose

Pose2 = tuple[float, float, float]

#: Longest chain followed from a frame up to the base.
_MAX_DEPTH = 32
#: Most frames of one robot's tree (a URDF has tens), and most lookups remembered.
MAX_FRAMES = 1024


class StaticFrames:
    """One robot's static transforms, child frame to ``(parent, pose in the parent)``."""

    def __init__(self) -> None:
        self._edges: dict[str, tuple[str, Pose2]] = {}
        self._cache: dict[tuple[str, str], Pose2 | None] = {}
        self._lock = threading.Lock()

    def add(self, parent: str, child: str, pose: Pose2) -> None:
        """A transform ``parent`` -> ``child``; a newer one of the same child replaces it."""
        child = child.lstrip("/")
        with self._lock:
            if child in self._edges or len(self._edges) < MAX_FRAMES:
                self._edges[child] = (parent.lstrip("/"), pose)
            self._cache.clear()

    def offset(self, base: str, frame: str) -> Pose2 | None:
        """The pose of ``frame`` in ``base``; ``None`` when the tree does not link them."""
        frame = frame.lstrip("/")
        if frame == base:
            return (0.0, 0.0, 0.0)
        with self._lock:
            key = (base, frame)
            if key not in self._cache:
                if len(self._cache) >= MAX_FRAMES:  # scans' frame ids are the robot's to invent
                    self._cache.clear()
                self._cache[key] = self._walk(base, frame)
            return self._cache[key]

    def _walk(self, base: str, frame: str) -> Pose2 | None:
        pose = np.zeros(3)
        cur = frame
        for _ in range(_MAX_DEPTH):
            edge = self._edges.get(cur)
            if edge is None:
                return None
            parent, in_parent = edge
            pose = compose(np.asarray(in_parent), pose)
            if parent == base:
                return (float(pose[0]), float(pose[1]), float(pose[2]))
            cur = parent
        return None
