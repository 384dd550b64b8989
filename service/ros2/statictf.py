"""Where a robot's laser is: its ``tf_static`` tree, from the base frame to the scan's frame.

Nav2 robots publish the fixed links (``base_footprint`` -> ``base_link`` -> ``base_scan``) on
``tf_static`` once, transient local; AMCL looks the laser's pose up in that tree. The wire
contract's LaserScan carries it as ``sensor_offset`` (x, y and yaw in the base frame), so each
scan's offset is the chain of static transforms from the base frame to the scan's
``header.frame_id``. A level laser is assumed: roll and pitch are dropped.

The front door holds one such tree per namespace (:class:`StaticTrees`); a scan whose frame its
robot's tree does not link to the base is taken at the base, said in the log once per frame
(for the first :data:`WARNED_FRAMES` frames of a robot) and counted.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable

import numpy as np

from rlutf.motion import compose
from service.keys import printable

log = logging.getLogger(__name__)

Pose2 = tuple[float, float, float]

#: Longest chain followed from a frame up to the base.
_MAX_DEPTH = 32
#: Most frames of one robot's tree (a URDF has tens), and most lookups remembered.
MAX_FRAMES = 1024
#: Scan frames with no tf_static link said in the log per robot (a robot's scans use one).
WARNED_FRAMES = 4


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


class StaticTrees:
    """The static transforms of each robot (namespace), and the laser's pose looked up in them.

    Args:
        base_frame: the frame whose pose is estimated (``ros2.base_frame``).
        most: namespaces held at most (they can be invented without end). When that many are
            held, the tree of a new namespace takes the place of the oldest tree of a namespace
            that is no robot (``is_robot``); with none, it is not held. (Trees of namespaces
            that never became robots were kept for good: tf_static on ``most`` made-up
            namespaces took the laser's pose from every ROS robot that came later.)
        is_robot: whether a namespace is a robot the front door holds.
    """

    def __init__(
        self, base_frame: str, most: int, is_robot: Callable[[str], bool] = lambda ns: True
    ) -> None:
        self.base_frame = base_frame
        self.most = most
        self.is_robot = is_robot
        self.laser_at_base = 0  # scans whose frame tf_static does not link to the base
        self._trees: dict[str, StaticFrames] = {}
        self._warned: dict[str, set[str]] = {}  # namespace: scan frames said to have no link
        self._lock = threading.Lock()

    def add(self, namespace: str, transforms: Iterable[tuple[str, str, Pose2]]) -> None:
        """A robot's static transforms ``(parent, child, pose in the parent)``."""
        with self._lock:
            tree = self._trees.get(namespace)
            full = tree is None and len(self._trees) >= self.most
            held = list(self._trees) if full else []  # oldest first
        victim: str | None = None
        if full:  # asked outside the lock: the roster tells this class of robots it drops
            victim = next((ns for ns in held if not self.is_robot(ns)), None)
            if victim is None:
                return
        with self._lock:
            tree = self._trees.get(namespace)
            if tree is None:
                if len(self._trees) >= self.most:
                    if victim is None or victim not in self._trees:
                        return  # another tree took the room meanwhile
                    del self._trees[victim]
                    self._warned.pop(victim, None)
                tree = self._trees[namespace] = StaticFrames()
        for parent, child, pose in transforms:
            tree.add(parent, child, pose)

    def offset(self, namespace: str, frame: str) -> Pose2 | None:
        """The pose of ``frame`` in the base frame; ``None`` when the robot's tree does not link
        them (or it has none)."""
        with self._lock:
            tree = self._trees.get(namespace)
        return None if tree is None else tree.offset(self.base_frame, frame)

    def laser_offset(self, namespace: str, robot_id: str, frame_id: str) -> Pose2:
        """The laser's pose in the base frame (zero if unknown: said and counted)."""
        found = self.offset(namespace, frame_id)
        if found is not None:
            return found
        if frame_id.lstrip("/") not in ("", self.base_frame):
            self.laser_at_base += 1
            with self._lock:  # said once per robot and frame, for a few frames a robot
                warned = self._warned.setdefault(namespace, set())
                say = frame_id not in warned and len(warned) < WARNED_FRAMES
                if say:
                    warned.add(frame_id)
            if say:
                log.warning(
                    "robot %s: no %s -> %s on tf_static yet; the laser is taken at the base%s",
                    robot_id,
                    self.base_frame,
                    printable(frame_id),  # the robot's text: no forged log line
                    "" if len(warned) < WARNED_FRAMES else " (its further frames not said)",
                )
        return (0.0, 0.0, 0.0)

    def forget(self, namespace: str) -> None:
        """Drop a robot's tree and what was said of it."""
        with self._lock:
            self._trees.pop(namespace, None)
            self._warned.pop(namespace, None)
