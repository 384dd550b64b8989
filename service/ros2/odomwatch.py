"""Whether a robot whose scans come has odometry on its Odometry topic (``odom_source = "odom"``).

The front door reads a robot's odometry as ``nav_msgs/Odometry`` on ``ros2.odom_topic`` by
default. A robot that publishes none there (many publish their odometry on ``tf`` only, ``odom``
-> ``base_footprint``) has its scans taken all the same: the engine localizes them with no
motion between them once the robot has an initial pose, ``amcl_pose`` goes out, but no ``map``
-> odom is published for it (there is no odometry to compose it with), and nothing told its
operator why. So when a robot's scans have come for :data:`SCAN_ODOMETRY_WAIT_S` with no Odometry
since, it is said (:class:`MissingOdometry`), naming the topic waited on and what to change; and
if the robot's tf carries its odometry (watched for a while from :data:`TF_WATCH_AFTER_S` into
the wait, :mod:`service.ros2.tfwatch`), saying to read it there (``--ros-odom tf``). Said once
per robot, and again (a wait later at the soonest) when its tf is then seen to carry its
odometry; a robot whose Odometry comes is forgotten (said again if it goes missing once more).
With the odometry read from tf, :class:`service.ros2.frames.TfOdometryFrames` says the like,
and this is :class:`NoOdometryWatch`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import zenoh

from service.config import Ros2Settings
from service.keys import printable
from service.ros2 import names
from service.ros2.frames import FRAMES_KEPT, Pair, odometry_like
from service.ros2.tfwatch import TfWatch

#: How long a robot's scans may come with no Odometry before it is said (s): far longer than an
#: odometry's period, and than the first scans of a robot that come before its first Odometry.
SCAN_ODOMETRY_WAIT_S = 2.0
#: How far into that wait the robot's tf starts to be watched (s): a robot whose Odometry is only
#: late is not watched, one without it has its tf seen before it is said.
TF_WATCH_AFTER_S = 0.5

Clock = Callable[[], int]


class OdometryWatch(Protocol):
    """What the front door tells of a robot's scans and odometry, and asks of it."""

    def start(self, session: zenoh.Session) -> None: ...
    def close(self) -> None: ...
    def scan(self, robot_id: str, namespace: str, now_ns: int) -> str | None: ...
    def odometry(self, robot_id: str) -> None: ...
    def forget(self, robot_id: str) -> None: ...
    def said(self) -> int: ...


@dataclass
class _Waiting:
    """A robot whose scans have come, and no Odometry, since ``since_ns``."""

    namespace: str
    since_ns: int
    watched: bool = False  # its tf is watched (or was)
    tf: Pair | None = None  # the transform most like its odometry seen on its tf
    said_ns: int | None = None  # when it was last said
    said_tf: Pair | None = None  # the transform named then


class MissingOdometry:
    """Says when a robot's scans come but no Odometry on ``ros2.odom_topic``.

    Only robots with no Odometry since their latest scans are remembered (a robot is forgotten
    as soon as its Odometry comes), at most ``kept`` of them.

    Args:
        settings: the ``ros2`` settings.
        clock: receive times (ns, increasing).
        max_payload_bytes: larger tf messages are not read.
        wait_ns: how long scans may come with no Odometry before it is said.
        watch_after_ns: how far into that wait the robot's tf starts to be watched.
        kept: robots remembered at most.
    """

    def __init__(
        self,
        settings: Ros2Settings,
        clock: Clock,
        max_payload_bytes: int,
        wait_ns: int = int(SCAN_ODOMETRY_WAIT_S * 1e9),
        watch_after_ns: int = int(TF_WATCH_AFTER_S * 1e9),
        kept: int = FRAMES_KEPT,
    ) -> None:
        self.settings = settings
        self.wait_ns = wait_ns
        self.watch_after_ns = watch_after_ns
        self.kept = kept
        self.tf = TfWatch(
            settings.domain_id, settings.tf_topic, self.on_tf, clock, max_payload_bytes
        )
        self._waiting: dict[str, _Waiting] = {}
        self._lock = threading.Lock()

    def start(self, session: zenoh.Session) -> None:
        """Watch robots' tf on ``session`` when asked."""
        self.tf.start(session)

    def close(self) -> None:
        """Watch no robot's tf any more."""
        self.tf.close()

    def scan(self, robot_id: str, namespace: str, now_ns: int) -> str | None:
        """The warning to give for a scan of a robot received at ``now_ns``, or ``None``."""
        with self._lock:
            w = self._waiting.get(robot_id)
            if w is None:
                if len(self._waiting) >= self.kept:
                    self._waiting.clear()  # ids invented without end: said once more at worst
                w = self._waiting[robot_id] = _Waiting(namespace, now_ns)
            waited = now_ns - w.since_ns
            if not w.watched and waited >= self.watch_after_ns:
                w.watched = self.tf.want(namespace, robot_id)  # False: as many watched already
            if waited < self.wait_ns:
                return None
            if w.said_ns is not None and (w.said_tf == w.tf or now_ns - w.said_ns < self.wait_ns):
                return None  # said; a change not at once, lest the service hold it back
            w.said_ns, w.said_tf = now_ns, w.tf
            tf, watched = w.tf, w.watched
        return self._missing_odometry(robot_id, namespace, tf, watched, waited)

    def odometry(self, robot_id: str) -> None:
        """An Odometry of a robot came: it is forgotten."""
        with self._lock:
            w = self._waiting.pop(robot_id, None)
        if w is not None and w.watched:
            self.tf.drop(w.namespace)

    def forget(self, robot_id: str) -> None:
        """Drop what is remembered of a robot (evicted, or idle)."""
        self.odometry(robot_id)

    def on_tf(self, robot_id: str, frames: list[Pair]) -> None:
        """A tf message of a robot whose tf is watched: the frames of its transforms."""
        s = self.settings
        found = odometry_like(frames, s.global_frame, s.odom_frame, s.base_frame)
        if found is None:
            return
        exact = found == (s.odom_frame, s.base_frame)
        with self._lock:
            w = self._waiting.get(robot_id)
            if w is None:
                return
            if w.tf is None or exact:
                w.tf = found
            namespace = w.namespace
        if exact:
            self.tf.drop(namespace)  # all there is to see

    def said(self) -> int:
        """How many robots have been said to have no odometry, and still have none."""
        with self._lock:
            return sum(1 for w in self._waiting.values() if w.said_ns is not None)

    def _missing_odometry(
        self, robot_id: str, namespace: str, tf: Pair | None, watched: bool, waited_ns: int
    ) -> str:
        s = self.settings
        topic = printable(names.join_topic(namespace, s.odom_topic))
        odom, base = s.odom_frame, s.base_frame
        said = (
            f"ROS robot {robot_id}: no odometry: for {waited_ns / 1e9:.1f} s its scans have come "
            f'but no nav_msgs/Odometry on {topic} (the settings ros2.odom_source = "odom" and '
            f'ros2.odom_topic = "{printable(s.odom_topic)}", every ROS robot\'s). Its scans are '
            f"localized without odometry (after an initial pose), and no {s.global_frame} -> "
            f"{odom} is published for it. "
        )
        tf_topic = printable(names.join_topic(namespace, s.tf_topic))
        if tf is None:
            seen = f"Its tf ({tf_topic}) showed no {odom} -> {base} either. " if watched else ""
            return said + (
                f"{seen}To fix: publish its nav_msgs/Odometry on {topic}, or set ros2.odom_topic "
                "to the topic it is on"
            )
        parent, child = printable(tf[0]), printable(tf[1])
        fix = '--ros-odom tf (ros2.odom_source = "tf")'
        if tf[0] != odom:
            fix += f' with ros2.odom_frame = "{parent}"'
        if tf[1] != base:
            fix += f' {"and" if tf[0] != odom else "with"} ros2.base_frame = "{child}"'
        return said + (
            f"Its tf ({tf_topic}) carries {parent} -> {child}: to fix, read the odometry from "
            f"tf: {fix}"
        )


class NoOdometryWatch:
    """No watch: the odometry is read from tf, where :class:`TfOdometryFrames` says it."""

    def start(self, session: zenoh.Session) -> None:
        """Nothing to start."""

    def close(self) -> None:
        """Nothing to close."""

    def scan(self, robot_id: str, namespace: str, now_ns: int) -> str | None:
        """Nothing to say."""
        return None

    def odometry(self, robot_id: str) -> None:
        """Nothing remembered."""

    def forget(self, robot_id: str) -> None:
        """Nothing remembered."""

    def said(self) -> int:
        """None said."""
        return 0


def odometry_watch(settings: Ros2Settings, clock: Clock, max_payload_bytes: int) -> OdometryWatch:
    """The watch the settings call for: on the Odometry topic, or none (odometry from tf)."""
    if settings.odom_source == "odom":
        return MissingOdometry(settings, clock, max_payload_bytes)
    return NoOdometryWatch()
