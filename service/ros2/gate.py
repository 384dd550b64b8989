"""Scans wait for the odometry at their stamp, as AMCL's tf message filter makes them wait.

A ROS robot's scans and odometry come on different topics, often from different nodes at
different rates, and the service reads them with different subscribers: a scan regularly
arrives before the odometry of its own instant (measured on loopback: 45 % of back-to-back
pairs). The engine takes the odometry up to a scan's stamp and never extrapolates, so such a
scan would be matched with the motion one reading short. The gate holds a robot's scan until
odometry at or after its stamp is in, or ``wait_ns`` has passed, or a newer scan arrives; a
robot that has sent no odometry is not held. Inputs are handed on in the order the engine must
see them, each with the time it is handed on as its receive time, so the log (ordered by
``log_time``) replays in that same order.

A robot's first scans wait for its first odometry too: after the service starts (a restart, a
new front door) a robot's scans can come before its odometry and its initial pose, and a robot
the service held before would be matched against its old odometry. A robot whose scan waited
``wait_ns`` without any odometry (one that sends none) is not held again until it sends some. An
initial pose stamped no later than a held scan goes on before it, as AMCL applies an initial
pose while the scan waits in its tf filter.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from schemas import LaserScan
from service.keys import InputKind, Message

Offer = Callable[[str, InputKind, bytes, Message, int], None]
Clock = Callable[[], int]


@dataclass(frozen=True)
class _Held:
    since_ns: int
    payload: bytes
    scan: LaserScan


class OdometryGate:
    """Orders each robot's inputs so that a scan follows the odometry at its stamp.

    Args:
        offer: where inputs go, in order (robot, kind, payload, message, receive time).
        clock: receive times (ns, increasing).
        wait_ns: longest a scan is held.
    """

    def __init__(self, offer: Offer, clock: Clock, wait_ns: int) -> None:
        self.offer = offer
        self.clock = clock
        self.wait_ns = wait_ns
        self.held_count = 0
        self.timed_out = 0
        self._lock = threading.Lock()
        self._latest: dict[str, int] = {}
        self._held: dict[str, _Held] = {}
        self._without: set[str] = set()  # robots whose scan timed out with no odometry yet

    def put(self, robot: str, kind: InputKind, payload: bytes, message: Message) -> None:
        """One validated input of a robot."""
        with self._lock:
            if kind == "odom":
                self._pass(robot, kind, payload, message)
                stamp = max(self._latest.get(robot, message.stamp_ns), message.stamp_ns)
                self._latest[robot] = stamp
                held = self._held.get(robot)
                if held is not None and held.scan.stamp_ns <= stamp:
                    self._release(robot)
                return
            held = self._held.get(robot)
            if kind != "scan" and held is not None and message.stamp_ns <= held.scan.stamp_ns:
                self._pass(robot, kind, payload, message)  # before the scan it precedes
                return
            self._release(robot)  # a newer scan, or a later initial pose, after a held scan
            latest = self._latest.get(robot)
            waits = robot not in self._without if latest is None else latest < message.stamp_ns
            if kind == "scan" and waits:
                assert isinstance(message, LaserScan)
                self._held[robot] = _Held(self.clock(), payload, message)
                self.held_count += 1
                return
            self._pass(robot, kind, payload, message)

    def flush(self, all_: bool = False) -> None:
        """Hand on the scans held longer than ``wait_ns`` (every one with ``all_``)."""
        with self._lock:
            now = self.clock()
            for robot in [
                r for r, h in self._held.items() if all_ or now - h.since_ns >= self.wait_ns
            ]:
                self.timed_out += 1
                if robot not in self._latest:
                    self._without.add(robot)  # sends no odometry: its scans go on as they come
                self._release(robot)

    def forget(self, robot: str) -> None:
        """Drop what is kept of a robot (evicted): a scan held for it goes unanswered."""
        with self._lock:
            self._latest.pop(robot, None)
            self._held.pop(robot, None)
            self._without.discard(robot)

    def _release(self, robot: str) -> None:
        held = self._held.pop(robot, None)
        if held is not None:
            self._pass(robot, "scan", held.payload, held.scan)

    def _pass(self, robot: str, kind: InputKind, payload: bytes, message: Message) -> None:
        self.offer(robot, kind, payload, message, self.clock())
