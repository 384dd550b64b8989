"""What the service puts on the bus besides answers: poses and Events, and their recording.

Poses go out on a publisher per robot that never delivers to this service's own subscribers
and drops rather than waits under congestion; Events go through the :class:`Outbox` (their own
thread), and both are recorded by the caller's thread, so the log never depends on what the
bus took.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh

from schemas import SCHEMA_NAMES, Event, EventCode, encode
from service.keys import Keys, printable
from service.live.outbox import Outbox
from service.logs.recording import Recorder

log = logging.getLogger(__name__)

EVENT_SCHEMA = SCHEMA_NAMES[Event]
JSON = zenoh.Encoding.APPLICATION_JSON


class Announcer:
    """Publishes and records a service's poses and Events.

    Args:
        keys: the key layout.
        recorder: where Events are recorded.
        clock: the service's receive clock, ns.
        outbox: the thread Events go out from.
    """

    def __init__(
        self, keys: Keys, recorder: Recorder, clock: Callable[[], int], outbox: Outbox
    ) -> None:
        self.keys = keys
        self.recorder = recorder
        self.clock = clock
        self.outbox = outbox
        self._session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self.closed = False

    def attach(self, session: zenoh.Session) -> None:
        """Publish poses on ``session`` from now on."""
        self._session = session

    def close(self) -> None:
        """Undeclare the pose publishers."""
        self.closed = True
        with self._lock:
            for pub in self._publishers.values():
                pub.undeclare()
            self._publishers.clear()

    def on_drop(self, robot: str, stamp_ns: int, received_ns: int) -> None:
        # Recorded (not published: under overload that would add load) so replay drops the
        # same scans; counted in health.
        ev = Event(
            stamp_ns=stamp_ns,
            level="info",
            code=EventCode.SCAN_DROPPED,
            key=self.keys.robot(robot, "scan"),
            message=f"scan {stamp_ns} replaced by a newer scan before processing",
        )
        self.recorder.record(
            self.keys.robot_events(robot), EVENT_SCHEMA, encode(ev), self.clock(), stamp_ns
        )

    def publish(self, key: str, payload: bytes, pose: bool = False) -> None:
        if self._session is None or (self.closed and pose):
            return
        try:
            if pose:
                pub = self._publishers.get(key)
                if pub is None:
                    with self._lock:
                        pub = self._publishers.get(key)
                        if pub is None:
                            pub = self._session.declare_publisher(
                                key,
                                encoding=JSON,
                                congestion_control=zenoh.CongestionControl.DROP,
                                priority=zenoh.Priority.DATA_HIGH,
                                # Not express: batched with other messages. Express, every
                                # pose took a slot of the link's short queue, and under CPU
                                # load Zenoh dropped some (measured at 50 robots: ~1 %).
                                express=False,
                                # Not to our own subscriber on {prefix}/robots/*/*: a callback
                                # per pose only to follow what _on_done already has.
                                allowed_destination=zenoh.Locality.REMOTE,
                            )
                            self._publishers[key] = pub
                pub.put(payload)
            else:
                self.outbox.put(key, payload)  # never waits: see service.live.outbox
        except zenoh.ZError:
            log.warning("could not publish on %s", key, exc_info=True)

    def event(
        self, key: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        stamp = now if now is not None else self.clock()
        ev = Event(stamp_ns=stamp, level=level, code=code, key=about, message=message)
        payload = encode(ev)
        log.log(
            logging.WARNING if level in ("warning", "error") else logging.INFO,
            "%s %s: %s",
            code,
            printable(about),  # a client's key: a newline in it must not forge a log line
            printable(message, 2000),
        )
        self.publish(key, payload)
        self.recorder.record(key, EVENT_SCHEMA, payload, self.clock(), stamp)

    def robot_event(
        self, robot: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        self.event(self.keys.robot_events(robot), level, code, about, message, now)

    def global_event(
        self, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        self.event(self.keys.events, level, code, about, message, now)
