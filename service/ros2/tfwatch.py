"""A few robots' tf, watched for a while, to see whether it carries their odometry.

With ``ros2.odom_source = "odom"`` the front door does not read tf: a robot's tf is its busiest
topic (its links and odometry, often tens of transforms tens of times a second), and a
subscriber on every robot's tf would bring the whole fleet's to the service over its links. But
a robot whose scans come without odometry often has it on tf only (``odom`` -> base, as many
drivers publish it), and its operator is to be told to read it there
(:mod:`service.ros2.odomwatch`). So that robot's tf alone is subscribed, for a while: until the
transform looked for is seen, the robot's odometry comes, or ``lifetime_ns`` has passed, and at
most ``most`` robots at once. A tf that does not decode is not an input here: it is left alone.

Subscribers are declared and undeclared on a thread of the watch's own, never in the Zenoh
callback that asks for them (see :mod:`service.ros2.roster`: a declaration can wait on the bus).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import zenoh

from schemas import SchemaError
from service.ros2 import convert, names
from service.ros2.entities import undeclare
from service.ros2.frames import Pair

log = logging.getLogger(__name__)

Frames = Callable[[str, list[Pair]], None]
"""Told of each tf message of a watched robot: robot id, the frames of its transforms."""
Clock = Callable[[], int]
#: Robots whose tf is watched at once.
TF_WATCHED = 16
#: Longest a robot's tf is watched (s): several seconds of a tf published at 1 Hz or more.
TF_WATCH_S = 10.0
#: How often the watch's thread looks for watches that have lasted ``lifetime_ns`` (s).
_TICK_S = 0.25


@dataclass(eq=False)
class _Watch:
    robot_id: str
    since_ns: int
    subscriber: Any = None
    declaring: bool = False  # its subscriber is being declared, or is
    ended: bool = False


class TfWatch:
    """Subscribers on the tf of a few robots, each for a while.

    Args:
        domain_id: the ROS domain.
        tf_topic: the tf topic's name, relative to a robot's namespace.
        on_frames: told of each tf message of a watched robot (in the Zenoh callback).
        clock: receive times (ns, increasing).
        max_payload_bytes: larger tf messages are not read.
        most: robots watched at once at most.
        lifetime_ns: longest a robot is watched.
    """

    def __init__(
        self,
        domain_id: int,
        tf_topic: str,
        on_frames: Frames,
        clock: Clock,
        max_payload_bytes: int,
        most: int = TF_WATCHED,
        lifetime_ns: int = int(TF_WATCH_S * 1e9),
    ) -> None:
        self.domain_id = domain_id
        self.tf_topic = tf_topic
        self.on_frames = on_frames
        self.clock = clock
        self.max_payload_bytes = max_payload_bytes
        self.most = most
        self.lifetime_ns = lifetime_ns
        self._watches: dict[str, _Watch] = {}  # by namespace
        self._lock = threading.Lock()
        self._work = threading.Condition(self._lock)
        self._changed = False
        self._closed = False
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None

    def start(self, session: zenoh.Session) -> None:
        """Declare the subscribers asked for on ``session``, on the watch's thread."""
        self._session = session
        self._thread = threading.Thread(target=self._run, name="rlutf-ros2-tfwatch", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Undeclare every subscriber."""
        with self._lock:
            self._closed = True
            self._work.notify()
        if self._thread is not None:
            self._thread.join(1.0)  # a declaration stuck on the bus ends with the session
        with self._lock:
            watches = list(self._watches.values())
            self._watches.clear()
        for w in watches:
            if w.subscriber is not None:
                undeclare(w.subscriber)

    def want(self, namespace: str, robot_id: str) -> bool:
        """Watch a robot's tf; ``False`` when ``most`` are watched already."""
        with self._lock:
            w = self._watches.get(namespace)
            if w is not None and not w.ended:
                return True
            if w is None and len(self._watches) >= self.most:
                return False
            if w is not None:  # ended, not yet undeclared: watched anew, for a full lifetime
                w.ended, w.since_ns = False, self.clock()
            else:
                self._watches[namespace] = _Watch(robot_id, self.clock())
            self._changed = True
            self._work.notify()
        return True

    def drop(self, namespace: str) -> None:
        """Stop watching a robot's tf (nothing if it is not watched)."""
        with self._lock:
            w = self._watches.get(namespace)
            if w is None or w.ended:
                return
            w.ended = True
            self._changed = True
            self._work.notify()

    def watched(self) -> int:
        """How many robots' tf is watched (or about to be)."""
        with self._lock:
            return sum(1 for w in self._watches.values() if not w.ended)

    def _run(self) -> None:
        while True:
            with self._lock:
                if not self._changed and not self._closed:
                    self._work.wait(_TICK_S if self._watches else None)
                if self._closed:
                    return
                self._changed = False
                now = self.clock()
                gone = [
                    (ns, w)
                    for ns, w in self._watches.items()
                    if w.ended or now - w.since_ns >= self.lifetime_ns
                ]
                for ns, _w in gone:
                    del self._watches[ns]
                new = [(ns, w) for ns, w in self._watches.items() if not w.declaring]
                for _ns, w in new:
                    w.declaring = True
            for _ns, w in gone:
                if w.subscriber is not None:
                    undeclare(w.subscriber)
            for ns, w in new:
                try:
                    self._declare(ns, w)
                except Exception:  # the thread must go on with the next robot
                    log.exception("watching the tf of ROS robot %s failed", w.robot_id)

    def _declare(self, namespace: str, w: _Watch) -> None:
        session = self._session
        assert session is not None
        topic = names.join_topic(namespace, self.tf_topic).strip("/")
        key = f"{self.domain_id}/{topic}/{names.dds_type(convert.TF_MESSAGE)}/*"
        subscriber = session.declare_subscriber(key, partial(self._on_sample, w.robot_id))
        with self._lock:
            if self._watches.get(namespace) is w:  # else ended while it was declared
                w.subscriber = subscriber
                return
        undeclare(subscriber)

    def _on_sample(self, robot_id: str, sample: zenoh.Sample) -> None:
        try:
            raw = sample.payload.to_bytes()
            if len(raw) > self.max_payload_bytes:
                return
            frames = convert.tf_frames(raw)
        except SchemaError:
            return  # not an input of ours: its odometry is not read from it
        except Exception:  # a callback must never raise into zenoh
            log.exception("a watched tf of ROS robot %s failed", robot_id)
            return
        self.on_frames(robot_id, frames)
