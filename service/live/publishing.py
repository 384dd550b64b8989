"""What the service puts on the bus besides answers: poses and Events, and their recording.

Poses go out on a publisher per robot that never delivers to this service's own subscribers
and drops rather than waits under congestion; Events go through the :class:`Outbox` (their own
thread), and both are recorded by the caller's thread, so the log never depends on what the
bus took.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

import zenoh

from schemas import SCHEMA_NAMES, Event, EventCode, encode
from schemas.fastevent import encode_scan_dropped
from service.keys import Keys, printable
from service.live.eventbudget import EventBudget
from service.live.outbox import Outbox
from service.logs.recording import Recorder

log = logging.getLogger(__name__)

EVENT_SCHEMA = SCHEMA_NAMES[Event]
JSON = zenoh.Encoding.APPLICATION_JSON
#: The encoding of ``{prefix}/service/{instance}/mapevidence`` (:mod:`service.evidence`).
BYTES = zenoh.Encoding.APPLICATION_OCTET_STREAM
EVIDENCE_LEAF = "/mapevidence"

#: Seconds a pose's put waits at most for the others of its round (checked after each batch):
#: the poses of the updates at hand are put back to back, at a fraction of the cost of lone
#: puts (:meth:`service.live.publishing.Announcer.hold`).
HOLD_S = 0.005


class PoseOut(Protocol):
    """Where poses go out (:class:`service.live.publishing.Announcer`)."""

    def hold(self) -> None: ...

    def release(self, older_than: float = 0.0) -> int: ...


class Announcer:
    """Publishes and records a service's poses and Events.

    Args:
        keys: the key layout.
        recorder: where Events are recorded.
        clock: the service's receive clock, ns.
        outbox: the thread Events go out from.
        on_robot_event: told of each robot Event sent (robot, code, stamp).
        budget: how many robots' Events of a code go out at most (:mod:`service.live.eventbudget`).
    """

    def __init__(
        self,
        keys: Keys,
        recorder: Recorder,
        clock: Callable[[], int],
        outbox: Outbox,
        on_robot_event: Callable[[str, str, int], None] | None = None,
        budget: EventBudget | None = None,
    ) -> None:
        self.keys = keys
        self.budget = budget or EventBudget()
        #: Told of each robot Event sent: robot, code, stamp (the per-robot view's reasons).
        self.on_robot_event = on_robot_event
        self.recorder = recorder
        self.clock = clock
        self.outbox = outbox
        self._session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self.closed = False
        # Pose puts held until release(), per thread that asked (see hold()): .held, .since.
        self._local = threading.local()

    def attach(self, session: zenoh.Session) -> None:
        """Publish poses on ``session`` from now on."""
        self._session = session

    def hold(self) -> None:
        """Hold the pose puts of the calling thread until it calls :meth:`release`.

        The threads that publish poses (the loop thread, :mod:`service.live.loop`; a worker's
        receiving thread, :class:`service.live.shards.ProcessShard`) put the poses of the
        updates at hand back to back: a put among others costs a fraction of a lone one, which
        wakes the bus's sending thread for itself (``python -m bench.wakeups``). Only the put is
        held: the recording, the pose query and the rest are not.
        """
        self._local.held = []
        self._local.since = 0.0

    def release(self, older_than: float = 0.0) -> int:
        """Put the calling thread's held poses, in the order they were made, unless the oldest
        was held less than ``older_than`` seconds. Returns the poses put."""
        local = self._local
        held: list[tuple[zenoh.Publisher, bytes]] | None = getattr(local, "held", None)
        if not held or (older_than and time.perf_counter() - local.since < older_than):
            return 0
        local.held = []
        for pub, payload in held:
            try:
                pub.put(payload)
            except zenoh.ZError:
                log.warning("could not publish a pose", exc_info=True)
        return len(held)

    def close(self) -> None:
        """Undeclare the pose publishers (what a thread holds, it puts before it ends)."""
        self.closed = True
        with self._lock:
            for pub in self._publishers.values():
                pub.undeclare()
            self._publishers.clear()

    def on_drop(self, robot: str, stamp_ns: int, received_ns: int) -> None:
        # Recorded (not published: under overload that would add load) so replay drops the
        # same scans; counted in health.
        # Written from a template (schemas.fastevent): a service behind on its scans drops many,
        # and the model cost each drop ~10 us more on the thread that is behind.
        # Logged at the dropped scan's own receive time (its log_time): a robot may stamp two
        # scans alike, and replay drops the very scan that was dropped here, not the first of
        # that stamp (service.logs.dropped, since 0.5.3).
        payload = encode_scan_dropped(self.keys.robot(robot, "scan"), stamp_ns)
        self.recorder.record(
            self.keys.robot_events(robot), EVENT_SCHEMA, payload, received_ns, stamp_ns
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
                held = getattr(self._local, "held", None)
                if held is not None:
                    if not held:
                        self._local.since = time.perf_counter()
                    held.append((pub, payload))
                    return
                pub.put(payload)
            else:
                # never waits: see service.live.outbox. The map health evidence the instances
                # share is a zstd frame, not JSON: labelled as bytes for tools that read rlutf/**
                binary = key.endswith(EVIDENCE_LEAF)
                self.outbox.put(key, payload, BYTES if binary else JSON)
        except zenoh.ZError:
            log.warning("could not publish on %s", key, exc_info=True)

    def event(
        self, key: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        stamp = now if now is not None else self.clock()
        ev = Event(stamp_ns=stamp, level=level, code=code, key=about, message=message)
        payload = encode(ev)
        _log(ev)
        self.publish(key, payload)
        self.recorder.record(key, EVENT_SCHEMA, payload, self.clock(), stamp)

    def recorder_event(self, ev: Event) -> None:
        """One of the recorder's own Events (``recording_failed`` when the disk is full, say):
        published and logged, not recorded (the recorder logged it already, when it could).
        Published only, it never reached the service's own output: a full disk stopped the
        audit log without a line in the journal."""
        _log(ev)
        self.publish(self.keys.events, encode(ev))

    def robot_event(
        self, robot: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        stamp = now if now is not None else self.clock()
        if self.on_robot_event is not None:  # first: the view holds it once the Event is out
            self.on_robot_event(robot, code, stamp)
        key = self.keys.robot_events(robot)
        if self.budget.admit(robot, level, code, about, message, stamp):
            self.event(key, level, code, about, message, stamp)
        elif code == EventCode.ROBOT_EVICTED:  # not sent, but replay forgets the robot there
            ev = Event(stamp_ns=stamp, level=level, code=code, key=about, message=message)
            self.recorder.record(key, EVENT_SCHEMA, encode(ev), self.clock(), stamp)

    def engine_event(self, robot: str, key: str, payload: bytes) -> None:
        """Publish an Event the engine made about ``robot`` (its caller records it), within the
        budget: a flood of new ids is a flood of ``not_initialized``."""
        code, about = _field(payload, b"code"), _field(payload, b"key")
        if self.budget.admit(robot, "", code, about, payload, self.clock()):
            self.publish(key, payload)

    def say_folded(self) -> None:
        """Send the Events that count those the budget held back, once their window is over
        (called once a second, by the sweeper's thread)."""
        for f in self.budget.due(self.clock()):
            self.global_event(f.level, f.code, f.about, f.message)

    def global_event(
        self, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        self.event(self.keys.events, level, code, about, message, now)


def _field(payload: bytes, name: bytes) -> str:
    """A string field of an encoded Event (compact JSON, as :func:`schemas.encode` writes it,
    its values the service's own), read without decoding it; ``""`` if absent."""
    start = payload.find(b'"' + name + b'":"')
    if start < 0:
        return ""
    start += len(name) + 4
    return payload[start : payload.find(b'"', start)].decode(errors="replace")


def _log(ev: Event) -> None:
    """An Event in the service's own log: warnings and errors as warnings."""
    log.log(
        logging.WARNING if ev.level in ("warning", "error") else logging.INFO,
        "%s %s: %s",
        ev.code,
        printable(ev.key),  # a client's key: a newline in it must not forge a log line
        printable(ev.message, 2000),
    )
