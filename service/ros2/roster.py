"""The ROS robots the front door holds, and what it declares for each on the bus.

A namespace becomes a robot once a message of it decodes: its id, the key naming its outputs
use (learned from its keys or forced by the settings), its recent odometry, and on the bus the
liveliness tokens of its topics (``ros2 topic list``) and the publishers of its outputs. At most
``max_robots`` are held: a new namespace past that is refused (an Event ``robot_limit`` a second)
once those idle for :data:`ROOM_IDLE_NS` (or ``idle_ns``, if shorter) are dropped: made-up
namespaces, a burst of them, held it full for ``robot_idle_s`` (an hour), and what a robot
dropped loses, its tokens, publishers and recent odometry, is stale after seconds without input
(the service keeps its state for ``robot_idle_s``). A robot dropped (idle, or evicted by the
service) loses its tokens and publishers; its next input makes it anew.

Tokens and publishers are declared and undeclared on a thread of the roster's own, never in the
Zenoh callback where a robot's first input arrives. zenoh-python forbids Zenoh calls in a
callback ("may lead to deadlocks", its docs/concepts.rst, Callbacks), and a declaration can wait
on the bus: it is sent with congestion control ``block``, so while one link's queue is full (a
robot's Wi-Fi gone, its process stopped) a declaration that goes to that link waits until zenoh
closes it (``block.wait_before_close``, 5 s; measured with zenoh-python 1.10.2). Made in the
callback, under the roster's lock, such a wait stalled that subscriber's intake for every robot
(and, its queue full, the link it reads) and the service's output thread (``on_pose``). A
robot's poses that come before its publishers are declared wait, the latest one, and go out
once they are, in order.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import zenoh

from service.config import Ros2Settings
from service.ros2 import convert, names
from service.ros2.attachment import Sequencer, gid_of
from service.ros2.entities import declare_publisher, limit_message, undeclare
from service.ros2.globalloc import EMPTY_SRV, SERVICE_QOS
from service.ros2.names import Distro
from service.ros2.trail import OdometryTrail

log = logging.getLogger(__name__)

Limit = Callable[[str, str, int], None]
"""Report a namespace refused, ``max_robots`` held: key, why, receive time (ns)."""
Forgotten = Callable[[str, str], None]
"""Told of a robot dropped: robot id, namespace."""
Send = Callable[[str, bytes, dict[str, "Publisher"]], None]
"""Publish a robot's pose (robot id, PoseEstimate payload) with its publishers by type."""
#: Least time between two ``robot_limit`` Events of the front door, ns.
LIMIT_EVENT_NS = 1_000_000_000
#: How long a namespace may send nothing before a full front door drops it to make room, ns.
ROOM_IDLE_NS = 10_000_000_000

Subscribed = tuple[str, str, names.Qos]
"""A topic the front door reads in each namespace: name, message type, QoS (for its token)."""


@dataclass
class Publisher:
    """One output of a robot: its key, its Zenoh publisher, its attachments' sequence."""

    key: str
    publisher: Any
    sequencer: Sequencer


@dataclass
class Entities:
    """What is declared on the bus for a robot: its publishers by message type, its tokens."""

    publishers: dict[str, Publisher] = field(default_factory=dict)
    tokens: list[Any] = field(default_factory=list)

    def undeclare(self) -> None:
        """Undeclare them all (each one that may be gone with its session too)."""
        for p in self.publishers.values():
            undeclare(p.publisher)
        for t in self.tokens:
            undeclare(t)


@dataclass
class Robot:
    """A ROS robot held: its namespace, id, map and key naming, and what is declared for it."""

    robot_id: str
    namespace: str
    map_id: str | None
    distro: Distro | None
    forced: bool
    odometry: OdometryTrail = field(default_factory=OdometryTrail)
    entities: Entities = field(default_factory=Entities)
    seen_ns: int = 0  # receive time of its latest input
    declared: Distro | None = None  # the naming its entities are declared with; None: not yet
    gone: bool = False  # dropped: its entities are to go
    queued: bool = False  # waits for the declaring thread
    pending: bytes | None = None  # its latest pose, waiting for its publishers


class Roster:
    """The robots of the ROS 2 front door, by namespace and by id.

    Args:
        settings: the ``ros2`` settings.
        subscribed: the topics read in each namespace (announced by each robot's tokens).
        max_robots: most robots (namespaces) held.
        idle_ns: ``robot_idle_s``: a robot idle for that long, or for :data:`ROOM_IDLE_NS`,
            makes room.
        on_limit: where a refusal is reported (at most once a second).
        forgotten: told of each robot dropped, after its entry goes.
        send: publishes a pose that waited for its robot's publishers (on the roster's thread).
    """

    def __init__(
        self,
        settings: Ros2Settings,
        subscribed: Sequence[Subscribed],
        max_robots: int,
        idle_ns: int,
        on_limit: Limit | None,
        forgotten: Forgotten,
        send: Send,
    ) -> None:
        self.settings = settings
        self.subscribed = list(subscribed)
        self.max_robots = max_robots
        self.idle_ns = idle_ns
        self.room_idle_ns = min(ROOM_IDLE_NS, idle_ns)
        self.on_limit = on_limit
        self.forgotten = forgotten
        self.send = send
        self.robots_refused = 0  # inputs of namespaces refused, max_robots held
        self._last_sweep = -LIMIT_EVENT_NS
        self._last_limit = -LIMIT_EVENT_NS
        self._robots: dict[str, Robot] = {}
        self._by_id: dict[str, Robot] = {}
        self._lock = threading.Lock()
        self._work = threading.Condition(self._lock)
        self._queue: deque[Robot] = deque()  # robots whose entities are to change
        self._closed = False
        self._thread: threading.Thread | None = None
        self._session: zenoh.Session | None = None
        self._zid = ""
        self._entity = 1  # entity ids of the tokens; 0 is the node

    def start(self, session: zenoh.Session) -> None:
        """Declare the robots' entities on ``session``, on the roster's thread."""
        self._session = session
        self._zid = str(session.zid())
        self._thread = threading.Thread(target=self._run, name="rlutf-ros2-declare", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Drop every robot, undeclaring its publishers and tokens."""
        with self._lock:
            self._closed = True
            self._work.notify()
        if self._thread is not None:
            self._thread.join(1.0)  # a declaration stuck on the bus ends with the session
        with self._lock:
            robots = {id(r): r for r in [*self._robots.values(), *self._queue]}.values()
            self._robots.clear()
            self._by_id.clear()
            self._queue.clear()
            for r in robots:
                r.gone = True
        for r in robots:
            r.entities.undeclare()

    def held(self, most: int = 50) -> dict[str, str]:
        """Robot id to namespace of the robots held, the first ``most`` by id."""
        with self._lock:
            held = sorted((r.robot_id, r.namespace) for r in self._robots.values())
        return dict(held[:most])

    def holds_namespace(self, namespace: str) -> bool:
        """Whether ``namespace`` is a robot held."""
        with self._lock:
            return namespace in self._robots

    def count(self) -> int:
        """How many robots are held."""
        return len(self._robots)

    def room(self, namespace: str, robot_id: str, key: str, received: int) -> bool:
        """Whether a namespace's input may be taken: its robot is held, or fewer than
        ``max_robots`` are; else it is refused, with an Event ``robot_limit`` a second."""
        with self._lock:
            if namespace in self._robots or len(self._robots) < self.max_robots:
                return True
            idle = []
            if received - self._last_sweep >= LIMIT_EVENT_NS:  # a look at most once a second
                self._last_sweep = received
                gone = received - self.room_idle_ns
                idle = [r.robot_id for r in self._robots.values() if r.seen_ns < gone]
        for gone_id in idle:  # owned elsewhere, or never taken: this instance evicts no one
            self.forget(gone_id)
        with self._lock:
            if len(self._robots) < self.max_robots:
                return True
            self.robots_refused += 1
            say = received - self._last_limit >= LIMIT_EVENT_NS
            if say:
                self._last_limit = received
        if say and self.on_limit is not None:
            why = limit_message(robot_id, self.max_robots, self.robots_refused)
            self.on_limit(key, why, received)
        return False

    def forget(self, robot_id: str) -> None:
        """Drop a robot: its tokens and publishers go (its next input makes it anew)."""
        with self._lock:
            r = self._by_id.pop(robot_id, None)
            if r is None:
                return
            self._robots.pop(r.namespace, None)
            r.gone = True
            self._enqueue(r)
        self.forgotten(robot_id, r.namespace)

    def robot(self, robot_id: str, namespace: str, distro: Distro, seen: int) -> Robot:
        """The robot of a namespace, made (and its entities declared) if new."""
        with self._lock:
            r = self._robots.get(namespace)
            if r is not None:
                r.seen_ns = seen
                if not r.forced and r.distro != distro:
                    log.info("ROS robot %s now uses %s key naming", robot_id, distro)
                    r.distro = distro
                    self._enqueue(r)
                return r
            over = self.settings.robot(namespace)
            chosen = over.distro or self.settings.distro
            forced = chosen != "auto"
            r = Robot(
                robot_id,
                namespace,
                over.map_id or self.settings.map_id,
                chosen if chosen != "auto" else distro,
                forced,
                seen_ns=seen,
            )
            self._robots[namespace] = r
            self._by_id[robot_id] = r
            self._enqueue(r)
            return r

    def add_odometry(self, robot: Robot, stamp_ns: int, pose: np.ndarray) -> None:
        """One odometry reading ``(x, y, theta)`` of a robot held."""
        with self._lock:
            robot.odometry.add(stamp_ns, pose)

    def publishers(self, robot_id: str, pose: bytes) -> dict[str, Publisher] | None:
        """A robot's publishers by message type, to publish ``pose`` with.

        ``None`` when the robot is not held here, or when its publishers are not declared yet:
        the pose then waits (the latest one) and goes to ``send`` once they are.
        """
        with self._lock:
            r = self._by_id.get(robot_id)
            if r is None:
                return None
            if r.declared is None or r.declared != r.distro:
                r.pending = pose
                return None
            return dict(r.entities.publishers)

    def odometry_at(self, robot_id: str, stamp_ns: int) -> np.ndarray | None:
        """A robot's odometry pose at a stamp; ``None`` with no reading (or no robot)."""
        with self._lock:
            r = self._by_id.get(robot_id)
            return None if r is None else r.odometry.at(stamp_ns)

    # ------------------------------------------------------------------------- entities
    def _enqueue(self, r: Robot) -> None:
        """The roster's thread is to bring ``r``'s entities in line with it (lock held)."""
        if not r.queued:
            r.queued = True
            self._queue.append(r)
            self._work.notify()

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._work.wait()
                if self._closed:
                    return
                r = self._queue.popleft()
                r.queued = False
            try:
                self._settle(r)
            except Exception:  # the thread must go on with the next robot
                log.exception("declaring the entities of ROS robot %s failed", r.robot_id)

    def _settle(self, r: Robot) -> None:
        """Undeclare what ``r`` has and declare what it needs; then send its waiting poses."""
        with self._lock:
            want = None if r.gone else r.distro
            if want is not None and want == r.declared:  # its naming changed, and back
                r.pending = None  # a newer pose goes out first, with the same publishers
                return
            old, r.entities, r.declared = r.entities, Entities(), None
        old.undeclare()
        if want is None or self._session is None:
            return
        made = self._declare(r.namespace, want)
        while True:
            with self._lock:
                if r.gone or r.distro != want or self._closed:  # changed meanwhile: queued again
                    r.entities = Entities()
                    break
                r.entities = made
                pose, r.pending = r.pending, None
                if pose is None:
                    r.declared = want  # from now on on_pose publishes with them itself
                    return
            # Poses that came meanwhile go out in order: a newer one waits until this is out.
            self.send(r.robot_id, pose, dict(made.publishers))
        made.undeclare()

    def _declare(self, namespace: str, distro: Distro) -> Entities:
        """The tokens of a robot's topics and its publishers, declared."""
        session = self._session
        assert session is not None
        s = self.settings
        entities: list[tuple[Literal["MP", "MS", "SS"], str, str, names.Qos]] = [
            ("MS", name, msgtype, qos) for name, msgtype, qos in self.subscribed
        ]
        entities.append(("MP", s.pose_topic, convert.POSE_COV, names.AMCL_POSE_QOS))
        if s.diagnostics_topic:
            entities.append(
                ("MP", s.diagnostics_topic, convert.DIAGNOSTIC_ARRAY, names.DIAGNOSTICS_QOS)
            )
        if s.publish_tf:
            entities.append(("MP", s.tf_topic, convert.TF_MESSAGE, names.TF_QOS))
        if s.global_localization_service:
            entities.append(("SS", s.global_localization_service, EMPTY_SRV, SERVICE_QOS))
        made = Entities()
        liveliness = session.liveliness()
        try:
            for kind, name, msgtype, q in entities:
                topic = names.join_topic(namespace, name)
                token = names.entity_token(
                    s.domain_id, self._zid, 0, self._entity, kind, topic, msgtype, distro, q
                )
                self._entity += 1
                made.tokens.append(liveliness.declare_token(token))
                if kind == "MP":
                    key = names.data_key(s.domain_id, topic, msgtype, distro)
                    made.publishers[msgtype] = Publisher(
                        key, declare_publisher(session, key, q), Sequencer(gid_of(token))
                    )
        except BaseException:
            made.undeclare()
            raise
        return made
