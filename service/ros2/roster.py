"""The ROS robots the front door holds, and what it declares for each on the bus.

A namespace becomes a robot once a message of it decodes: its id, the key naming its outputs
use (learned from its keys or forced by the settings), its recent odometry, and on the bus the
liveliness tokens of its topics (``ros2 topic list``) and the publishers of its outputs. At most
``max_robots`` are held: a new namespace past that is refused (an Event ``robot_limit`` a second)
once those idle for ``idle_ns`` are dropped. A robot dropped (idle, or evicted by the service)
loses its tokens and publishers; its next input makes it anew.
"""

from __future__ import annotations

import logging
import threading
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
#: Least time between two ``robot_limit`` Events of the front door, ns.
LIMIT_EVENT_NS = 1_000_000_000

Subscribed = tuple[str, str, names.Qos]
"""A topic the front door reads in each namespace: name, message type, QoS (for its token)."""


@dataclass
class Publisher:
    """One output of a robot: its key, its Zenoh publisher, its attachments' sequence."""

    key: str
    publisher: Any
    sequencer: Sequencer


@dataclass
class Robot:
    """A ROS robot held: its namespace, id, map and key naming, and what is declared for it."""

    robot_id: str
    namespace: str
    map_id: str | None
    distro: Distro | None
    forced: bool
    odometry: OdometryTrail = field(default_factory=OdometryTrail)
    publishers: dict[str, Publisher] = field(default_factory=dict)
    tokens: list[Any] = field(default_factory=list)
    seen_ns: int = 0  # receive time of its latest input


class Roster:
    """The robots of the ROS 2 front door, by namespace and by id.

    Args:
        settings: the ``ros2`` settings.
        subscribed: the topics read in each namespace (announced by each robot's tokens).
        max_robots: most robots (namespaces) held.
        idle_ns: how long a robot may send nothing before it makes room (``robot_idle_s``).
        on_limit: where a refusal is reported (at most once a second).
        forgotten: told of each robot dropped, after its entry goes.
    """

    def __init__(
        self,
        settings: Ros2Settings,
        subscribed: Sequence[Subscribed],
        max_robots: int,
        idle_ns: int,
        on_limit: Limit | None,
        forgotten: Forgotten,
    ) -> None:
        self.settings = settings
        self.subscribed = list(subscribed)
        self.max_robots = max_robots
        self.idle_ns = idle_ns
        self.on_limit = on_limit
        self.forgotten = forgotten
        self.robots_refused = 0  # inputs of namespaces refused, max_robots held
        self._last_sweep = -LIMIT_EVENT_NS
        self._last_limit = -LIMIT_EVENT_NS
        self._robots: dict[str, Robot] = {}
        self._by_id: dict[str, Robot] = {}
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self._zid = ""
        self._entity = 1  # entity ids of the tokens; 0 is the node

    def start(self, session: zenoh.Session) -> None:
        """Declare the robots' entities on ``session`` from now on."""
        self._session = session
        self._zid = str(session.zid())

    def close(self) -> None:
        """Drop every robot, undeclaring its publishers and tokens."""
        with self._lock:
            robots = list(self._robots.values())
            self._robots.clear()
            self._by_id.clear()
        for r in robots:
            _undeclare_all(r)

    def held(self, most: int = 50) -> dict[str, str]:
        """Robot id to namespace of the robots held, the first ``most`` by id."""
        with self._lock:
            held = sorted((r.robot_id, r.namespace) for r in self._robots.values())
        return dict(held[:most])

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
                gone = received - self.idle_ns
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
        self.forgotten(robot_id, r.namespace)
        _undeclare_all(r)

    def robot(self, robot_id: str, namespace: str, distro: Distro, seen: int) -> Robot:
        """The robot of a namespace, made (and its entities declared) if new."""
        with self._lock:
            r = self._robots.get(namespace)
            if r is not None:
                r.seen_ns = seen
                if not r.forced and r.distro != distro:
                    log.info("ROS robot %s now uses %s key naming", robot_id, distro)
                    self._redeclare(r, distro)
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
            self._declare(r)
            return r

    def add_odometry(self, robot: Robot, stamp_ns: int, pose: np.ndarray) -> None:
        """One odometry reading ``(x, y, theta)`` of a robot held."""
        with self._lock:
            robot.odometry.add(stamp_ns, pose)

    def publishers(self, robot_id: str) -> dict[str, Publisher] | None:
        """A robot's publishers by message type; ``None`` when it is not held here."""
        with self._lock:
            r = self._by_id.get(robot_id)
            return None if r is None else dict(r.publishers)

    def odometry_at(self, robot_id: str, stamp_ns: int) -> np.ndarray | None:
        """A robot's odometry pose at a stamp; ``None`` with no reading (or no robot)."""
        with self._lock:
            r = self._by_id.get(robot_id)
            return None if r is None else r.odometry.at(stamp_ns)

    # ------------------------------------------------------------------------- entities
    def _declare(self, r: Robot) -> None:
        """Tokens of the robot's topics and its publishers (lock held)."""
        session = self._session
        if session is None or r.distro is None:
            return
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
        liveliness = session.liveliness()
        for kind, name, msgtype, q in entities:
            topic = names.join_topic(r.namespace, name)
            token = names.entity_token(
                s.domain_id, self._zid, 0, self._entity, kind, topic, msgtype, r.distro, q
            )
            self._entity += 1
            r.tokens.append(liveliness.declare_token(token))
            if kind == "MP":
                key = names.data_key(s.domain_id, topic, msgtype, r.distro)
                r.publishers[msgtype] = Publisher(
                    key, declare_publisher(session, key, q), Sequencer(gid_of(token))
                )

    def _redeclare(self, r: Robot, distro: Distro) -> None:
        _undeclare_all(r)
        r.publishers.clear()
        r.tokens.clear()
        r.distro = distro
        self._declare(r)


def _undeclare_all(r: Robot) -> None:
    for p in r.publishers.values():
        undeclare(p.publisher)
    for t in r.tokens:
        undeclare(t)
