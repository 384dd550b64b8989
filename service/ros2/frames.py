"""Whether a robot's odometry is in the frames the front door publishes ``map`` -> odom for.

The service publishes ``map`` -> ``ros2.odom_frame`` on each robot's ``tf``. A robot whose
``nav_msgs/Odometry`` has another ``header.frame_id`` (``wheel_odom``, say) is localized all
the same, since the motion between two readings does not depend on the frame's name, but that
transform then names a frame the robot's tf tree lacks, and Nav2 on the robot never links
``map`` to its base. Such odometry is taken, not refused, and said once per robot, and again
when its frames change.

``child_frame_id`` names no frame the service publishes: the pose is that of ``ros2.base_frame``
(the laser's pose is looked up from it on ``tf_static``) and ``map`` -> odom is that pose
composed with the inverse of the odometry. So another child frame matters only when it is
elsewhere in the plane than the base frame: ``map`` -> odom is then off by that offset. Nav2
robots' usual ``base_link`` is above ``base_footprint`` (REP 120: the footprint is its projection
on the ground), the same in the plane, and is not said; a child frame that ``tf_static`` puts
elsewhere in the plane is.

With the odometry read from tf (``ros2.odom_source = "tf"``), a robot whose tf carries its
odometry under other frames (``odom`` -> ``base_link`` where ``base_footprint`` is expected,
``wheel_odom`` -> ``base_footprint``) has no odometry at all: its scans are localized without
it and no ``map`` -> odom is published. A robot's tf carries other transforms too (its links,
the ``map`` -> odom published for it), often in messages of their own, so this is said only when
its tf has carried transforms but not its odometry for :data:`TF_ODOMETRY_WAIT_S`; said once per
robot, and again when other frames are seen (:class:`TfOdometryFrames`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

from service.keys import printable
from service.ros2.statictf import Pose2

#: Robots whose frames are remembered: ids can be invented without end, so the memory starts
#: again when full (at worst the frames of a robot are said once more), as the service's Gate.
FRAMES_KEPT = 8192
#: Characters of a frame id kept and quoted (a frame id is the robot's text, of any length).
FRAME_CHARS = 200
#: How long a robot's tf may carry transforms, none of them its odometry, before it is said (s):
#: longer than an odometry's period, so the robot's other links between two readings are not.
TF_ODOMETRY_WAIT_S = 2.0
#: Distinct transforms (parent, child) of a robot remembered and quoted.
PAIRS_KEPT = 8
#: Offsets in the plane below these are none (m, rad): tf_static's floats of a zero link.
_TINY_M = 1e-3
_TINY_RAD = 1e-3


class OdometryFrames:
    """Says when a robot's odometry is in other frames than the ones the service assumes.

    Args:
        odom_frame: ``ros2.odom_frame``, the child frame of the ``map`` -> odom published.
        base_frame: ``ros2.base_frame``, the frame whose pose the service estimates.
        kept: robots remembered at most.
    """

    def __init__(self, odom_frame: str, base_frame: str, kept: int = FRAMES_KEPT) -> None:
        self.odom_frame = odom_frame
        self.base_frame = base_frame
        self.kept = kept
        self._said: dict[str, tuple[str | None, str | None]] = {}
        self._lock = threading.Lock()

    def check(
        self, robot_id: str, frame_id: str, child_frame_id: str, child_offset: Pose2 | None
    ) -> str | None:
        """The warning to give for one Odometry of a robot, or ``None``.

        A warning is given when the robot's frames are wrong in a way other than the last one
        said for it (its first Odometry, or a change).

        Args:
            robot_id: the robot.
            frame_id: the Odometry's ``header.frame_id`` (without a leading slash).
            child_frame_id: its ``child_frame_id`` (without a leading slash).
            child_offset: the child frame's pose in the base frame from the robot's
                ``tf_static`` (``None``: unknown).
        """
        frame_id, child = frame_id[:FRAME_CHARS], child_frame_id[:FRAME_CHARS]
        wrong_odom = frame_id if frame_id != self.odom_frame else None
        wrong_child = None
        if child != self.base_frame and child_offset is not None and displaced(child_offset):
            wrong_child = child
        state = (wrong_odom, wrong_child)
        with self._lock:
            if self._said.get(robot_id, (None, None)) == state:
                return None
            if robot_id not in self._said and len(self._said) >= self.kept:
                self._said.clear()
            self._said[robot_id] = state
        if state == (None, None):
            return None  # right again: said again if it goes wrong once more
        problems = []
        if wrong_odom is not None:
            problems.append(self._odom_problem(wrong_odom))
        if wrong_child is not None and child_offset is not None:
            problems.append(self._child_problem(wrong_child, child_offset))
        return f"ROS robot {robot_id}: " + "; also, ".join(problems)

    def forget(self, robot_id: str) -> None:
        """Drop what is remembered of a robot (its next Odometry is checked anew)."""
        with self._lock:
            self._said.pop(robot_id, None)

    def _odom_problem(self, seen: str) -> str:
        seen_, odom = printable(seen), self.odom_frame
        return (
            f"its odometry is in frame '{seen_}', not '{odom}' (the setting ros2.odom_frame). "
            f"Its poses are right, but the map -> {odom} transform the service publishes on its "
            f"tf names a frame its tf tree lacks, so Nav2 on it finds no map -> "
            f'{self.base_frame}. Set ros2.odom_frame = "{seen_}" (every ROS robot\'s: there is '
            f"no per-robot setting), or publish the robot's odometry in '{odom}'"
        )

    def _child_problem(self, child: str, offset: Pose2) -> str:
        child_, base = printable(child), self.base_frame
        x, y, yaw = offset
        return (
            f"its odometry is of frame '{child_}', not '{base}' (the setting ros2.base_frame), "
            f"and its tf_static puts '{child_}' at x {x:.3f} m, y {y:.3f} m, yaw {yaw:.3f} rad "
            f"from '{base}': the map -> {self.odom_frame} transform the service publishes is off "
            f'by that offset. Set ros2.base_frame = "{child_}" (every ROS robot\'s), or publish '
            f"the odometry of '{base}'"
        )


def displaced(offset: Pose2) -> bool:
    """Whether a pose in the plane is not the identity (beyond tf_static's float noise)."""
    x, y, yaw = offset
    return abs(x) > _TINY_M or abs(y) > _TINY_M or abs(math.remainder(yaw, math.tau)) > _TINY_RAD


Pair = tuple[str, str]
"""A transform's frames: ``(parent, child)``."""


def odometry_like(
    pairs: Iterable[Pair], global_frame: str, odom_frame: str, base_frame: str
) -> Pair | None:
    """The transform of ``pairs`` most like a robot's odometry, frame ids cut to
    :data:`FRAME_CHARS`: ``odom_frame`` -> ``base_frame`` itself, else the first from
    ``odom_frame`` (``odom`` -> ``base_link``) or to ``base_frame`` (``wheel_odom`` ->
    ``base_footprint``); ``None`` if none is (``global_frame`` -> ``odom_frame`` is not the
    robot's)."""
    best = None
    for parent, child in pairs:
        pair = (parent[:FRAME_CHARS], child[:FRAME_CHARS])
        if pair == (odom_frame, base_frame):
            return pair
        near = parent == odom_frame or child == base_frame
        if best is None and near and pair != (global_frame, odom_frame):
            best = pair
    return best


@dataclass
class _Missing:
    """A robot whose tf has carried transforms, none of them its odometry, since ``since_ns``."""

    since_ns: int
    seen: dict[Pair, None] = field(default_factory=dict)  # in the order seen
    said: frozenset[Pair] = frozenset()  # the transforms named in the last warning


class TfOdometryFrames:
    """Says when a robot's tf carries transforms but not its odometry (``odom_source = "tf"``).

    Only robots whose odometry is missing are remembered (a robot is forgotten as soon as its
    odometry comes), at most ``kept`` of them, with ``pairs_kept`` transforms each.

    Args:
        global_frame: ``ros2.global_frame``: ``global_frame`` -> ``odom_frame`` is the transform
            the service (or an AMCL beside it) publishes on the robot's tf, not the robot's.
        odom_frame: ``ros2.odom_frame``, the parent frame of the odometry.
        base_frame: ``ros2.base_frame``, its child frame.
        wait_ns: how long the robot's tf may carry other transforms only before it is said.
        kept: robots remembered at most.
        pairs_kept: transforms remembered (and named) per robot at most.
    """

    def __init__(
        self,
        global_frame: str,
        odom_frame: str,
        base_frame: str,
        wait_ns: int,
        kept: int = FRAMES_KEPT,
        pairs_kept: int = PAIRS_KEPT,
    ) -> None:
        self.ours = (global_frame, odom_frame)
        self.odom_frame = odom_frame
        self.base_frame = base_frame
        self.wait_ns = wait_ns
        self.kept = kept
        self.pairs_kept = pairs_kept
        self._missing: dict[str, _Missing] = {}
        self._lock = threading.Lock()

    def check(
        self, robot_id: str, found: bool, transforms: Iterable[Pair], now_ns: int
    ) -> str | None:
        """The warning to give for one tf message of a robot, or ``None``.

        Args:
            robot_id: the robot.
            found: whether the message carried the robot's odometry.
            transforms: the frames of its transforms (without a leading slash).
            now_ns: when it was received (ns).
        """
        if found:
            with self._lock:
                self._missing.pop(robot_id, None)
            return None
        pairs = [(p[:FRAME_CHARS], c[:FRAME_CHARS]) for p, c in transforms if (p, c) != self.ours]
        if not pairs:
            return None  # only map -> odom: nothing of the robot's own
        with self._lock:
            state = self._missing.get(robot_id)
            if state is None:
                if len(self._missing) >= self.kept:
                    self._missing.clear()
                state = self._missing[robot_id] = _Missing(now_ns)
            for pair in pairs:
                if len(state.seen) >= self.pairs_kept:
                    break
                state.seen[pair] = None
            if now_ns - state.since_ns < self.wait_ns or state.said >= state.seen.keys():
                return None
            state.said = frozenset(state.seen)
            seen, waited_ns = list(state.seen), now_ns - state.since_ns
        return self._missing_odometry(robot_id, seen, waited_ns)

    def forget(self, robot_id: str) -> None:
        """Drop what is remembered of a robot (its next tf is checked anew)."""
        with self._lock:
            self._missing.pop(robot_id, None)

    def said(self) -> int:
        """How many robots have been said to have no odometry, and still have none."""
        with self._lock:
            return sum(1 for m in self._missing.values() if m.said)

    def _missing_odometry(self, robot_id: str, seen: list[Pair], waited_ns: int) -> str:
        (global_, odom), base = self.ours, self.base_frame
        listed = ", ".join(f"{printable(p)} -> {printable(c)}" for p, c in seen)
        fixes = [f'set ros2.base_frame = "{printable(c)}"' for p, c in seen if p == odom]
        fixes += [f'set ros2.odom_frame = "{printable(p)}"' for p, c in seen if c == base]
        fixes += [
            f"publish {odom} -> {base} on its tf",
            'read its nav_msgs/Odometry instead (ros2.odom_source = "odom", --ros-odom odom)',
        ]
        return (
            f"ROS robot {robot_id}: no odometry: for {waited_ns / 1e9:.1f} s its tf has carried "
            f"{listed}, but no {odom} -> {base} (the settings ros2.odom_frame and "
            f'ros2.base_frame, every ROS robot\'s; read with ros2.odom_source = "tf"). Its '
            f"scans are localized without odometry, and no {global_} -> {odom} is published "
            f"for it. To fix: {', or '.join(fixes)}"
        )
