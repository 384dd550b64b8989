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
"""

from __future__ import annotations

import math
import threading

from service.keys import printable
from service.ros2.statictf import Pose2

#: Robots whose frames are remembered: ids can be invented without end, so the memory starts
#: again when full (at worst the frames of a robot are said once more), as the service's Gate.
FRAMES_KEPT = 8192
#: Characters of a frame id kept and quoted (a frame id is the robot's text, of any length).
FRAME_CHARS = 200
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
        if child != self.base_frame and child_offset is not None and _displaced(child_offset):
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


def _displaced(offset: Pose2) -> bool:
    x, y, yaw = offset
    return abs(x) > _TINY_M or abs(y) > _TINY_M or abs(math.remainder(yaw, math.tau)) > _TINY_RAD
