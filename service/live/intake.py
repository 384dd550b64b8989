"""Inputs on the bus: from a robot key to the robot's owner, with everything checked first.

A Zenoh callback only decodes, validates and hands the input on (``STYLE.md``): what the key
says (a robot id, an input leaf), whether this instance owns the robot, whether the service
takes one more robot id (:class:`service.live.admission.Gate`), the message's schema and its
stamp. Rejections are Events; nothing here waits on the bus.
"""

from __future__ import annotations

from typing import Protocol

import zenoh

from schemas import EventCode, SchemaError, decode
from service.cluster.membership import Membership
from service.cluster.ownership import Ownership
from service.config import Settings
from service.keys import INPUT_KINDS, MODELS, InputKind, KeyError_, Keys, Message
from service.live.admission import Gate, Sweeper
from service.live.keywatch import KeyWatch
from service.live.stats import Stats
from service.ros2 import names
from service.ros2.frontdoor import Ros2FrontDoor

#: Robot keys the intake keeps split at most (a fleet uses a few per robot).
KEYS_SPLIT = 8192
#: Robot keys declared to Zenoh at most (:meth:`Intake.declare_keys`): a few per robot of a fleet
#: of 1,000; past it (ids invented without end) keys are taken in undeclared, until the split keys
#: start again.
KEYS_DECLARED = 4096
#: Inputs that are an operator's request, answered each time (`rlutf initialpose` waits for it).
REQUESTS = frozenset(("initialpose", "relocalize"))


class Service(Protocol):
    """What the intake needs of :class:`service.live.node.LocalizationService`."""

    settings: Settings
    keys: Keys
    stats: Stats
    ownership: Ownership
    membership: Membership
    gate: Gate
    sweeper: Sweeper
    keywatch: KeyWatch

    def clock(self) -> int: ...

    def robots_held(self) -> int: ...

    def holds(self, robot: str) -> bool: ...

    def _robot_event(
        self, robot: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None: ...

    def _global_event(
        self, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None: ...


class Intake:
    """The service's input callbacks (JSON keys) and the ROS 2 front door's hand-over."""

    def __init__(self, svc: Service) -> None:
        self.svc = svc
        # Robot keys already split (robot, leaf): every sample of a fleet is on one of a few
        # keys per robot, and splitting and checking the id was a tenth of the intake's time.
        self._split: dict[str, tuple[str, str]] = {}
        self._session: zenoh.Session | None = None
        self._declared: list[zenoh.KeyExpr] = []

    def declare_keys(self, session: zenoh.Session) -> None:
        """Declare each robot key to Zenoh as its first sample comes in (:data:`KEYS_DECLARED` at
        most), from the thread that drains the input channel (never from a Zenoh callback).

        Zenoh keeps a sample's route (the subscribers it goes to) only for a key some session of
        its process declared; for any other key it matches the key against every declared one,
        for every sample. A service process declares a few keys per robot it publishes for
        (poses, Events), so that matching grows with the fleet: in the second process of a host
        it was a third of its Zenoh threads' CPU at 200 robots (0.066 against 0.037 ms a scan
        with the keys declared; BENCHMARKS.md, "Where the service's CPU goes by code"). In the
        host, the router, the same holds for robots that put on their keys without declaring
        a publisher.
        """
        self._session = session

    def _declare(self, key: str) -> None:
        if self._session is None or len(self._declared) >= KEYS_DECLARED:
            return
        try:
            self._declared.append(self._session.declare_keyexpr(key))
        except zenoh.ZError:  # the session closing: nothing to keep a route for
            self._session = None

    def _undeclare_all(self) -> None:
        session, declared, self._declared = self._session, self._declared, []
        if session is None:
            return
        for expr in declared:
            try:
                session.undeclare(expr)
            except zenoh.ZError:
                return

    def on_robot_sample(self, sample: zenoh.Sample) -> None:
        """Subscriber callback on `{prefix}/robots/*/{leaf}`: check, then hand to the owner."""
        if sample.kind != zenoh.SampleKind.PUT:
            return  # DELETEs are not inputs: the KeyWatch reports them
        svc = self.svc
        key = str(sample.key_expr)
        parsed = self._split.get(key)
        if parsed is None:
            try:
                parsed = svc.keys.parse_robot_key(key)
            except KeyError_ as err:
                if svc.ownership.ready and svc.membership.owns_key(key):  # one instance reports
                    svc.stats.add("received")
                    svc.stats.add("rejected")
                    code = EventCode.INVALID_KEY  # one Event a second: ids are a client's to invent
                    svc.keywatch.limited("invalid_id", "error", code, key, str(err), svc.clock())
                return
            if parsed is None:
                return
            if len(self._split) >= KEYS_SPLIT:  # ids invented without end: start again
                self._split.clear()
                self._undeclare_all()
            self._split[key] = parsed
            self._declare(key)
        robot, leaf = parsed
        limit = svc.settings.max_payload_bytes
        if leaf == "pose":  # every instance follows every pose, for handovers
            problem = svc.ownership.follow_pose(robot, sample.payload.to_bytes(), limit)
            if problem:
                received = svc.clock()
                if svc.gate.allow_event(received):
                    code = EventCode.STAMP_REJECTED
                    svc._robot_event(robot, "warning", code, key, problem, received)
            return
        if leaf not in INPUT_KINDS:
            return  # events, or keys of other tools
        payload = sample.payload.to_bytes()
        if not svc.ownership.owns(robot):
            svc.ownership.ignore(robot, leaf, payload, limit)
            return
        received = svc.clock()
        svc.stats.add("received")
        if self._over_limit(robot, key, received, leaf):
            return
        try:
            msg = decode(MODELS[leaf], payload, max_bytes=limit)
        except SchemaError as err:
            svc.stats.add("rejected")
            self._invalid(robot, leaf, key, str(err), received)
            return
        if self._stamp_refused(robot, key, msg.stamp_ns, received):
            return
        svc.ownership.offer(robot, leaf, payload, msg, received)

    def _over_limit(self, robot: str, key: str, at: int, kind: str) -> bool:
        """Whether a new robot is refused (``max_robots`` held): counted, an Event a second. An
        input that places a robot first evicts a robot never placed, if there is one."""
        svc = self.svc
        refused = svc.gate.refuse_new(svc, robot, at)
        if refused is not None and kind in REQUESTS and svc.sweeper.make_room():
            refused = svc.gate.refuse_new(svc, robot, at)
        if refused is None:
            return False
        svc.stats.add("rejected")
        if refused:
            svc._global_event("warning", EventCode.ROBOT_LIMIT, key, refused, at)
        return True

    def _stamp_refused(self, robot: str, key: str, stamp_ns: int, at: int) -> bool:
        """Whether a stamp is refused (``max_stamp_ahead_s``): counted; an Event at most one per
        robot and ``event_interval_s`` (a robot whose clock is ahead sends every message so
        stamped), the next counting those held back, and at most ten a second in all."""
        svc = self.svc
        problem = svc.gate.stamp_problem(stamp_ns, at)
        if problem is None:
            return False
        svc.stats.add("rejected")
        held = svc.gate.rejection(robot, EventCode.STAMP_REJECTED, at)
        if held is not None and svc.gate.allow_event(at):
            more = f" ({held} more like it since the last such Event)" if held else ""
            svc._robot_event(robot, "error", EventCode.STAMP_REJECTED, key, problem + more, at)
        return True

    def front_door(self) -> Ros2FrontDoor:
        """The ROS 2 front door, handing its inputs to :meth:`offer`."""
        s = self.svc.settings
        return Ros2FrontDoor(
            s.ros2,
            self.offer,
            self.reject,
            self.svc.clock,
            s.max_payload_bytes,
            self.svc.keys,
            s.max_robots,
            self.limit,
            int(s.robot_idle_s * 1e9),
            self.warn,
        )

    def offer(self, robot: str, kind: InputKind, payload: bytes, msg: Message, at: int) -> None:
        """A validated input from the ROS 2 front door (``payload``: its JSON encoding), taken
        as a JSON one is: within ``max_robots`` and ``max_stamp_ahead_s``."""
        svc = self.svc
        if not svc.ownership.owns(robot):
            svc.ownership.ignore(robot, kind, payload, svc.settings.max_payload_bytes)
            return
        svc.stats.add("received")
        key = svc.keys.robot(robot, kind)
        if self._over_limit(robot, key, at, kind) or self._stamp_refused(
            robot, key, msg.stamp_ns, at
        ):
            return
        svc.ownership.offer(robot, kind, payload, msg, at)

    def limit(self, key: str, message: str, at: int) -> None:
        """A ROS 2 namespace refused by the front door, ``max_robots`` held."""
        self.svc.stats.add("received")
        self.svc.stats.add("rejected")
        self.svc._global_event("warning", EventCode.ROBOT_LIMIT, key, message, at)

    def warn(self, robot: str, code: str, key: str, message: str, at: int) -> None:
        """Input of a ROS robot not as the settings expect (its odometry's frames): an Event
        ``code`` (``frame_mismatch``, ``odometry_not_found``) from the robot's owner, at most
        one per ``event_interval_s`` and code (frames that change at every message are not an
        Event each)."""
        svc = self.svc
        if not svc.ownership.owns(robot):
            return  # its owner says it
        held = svc.gate.rejection(robot, code, at)
        if held is None:
            return
        more = f" ({held} more like it since the last such Event)" if held else ""
        svc._robot_event(robot, "warning", code, key, message + more, at)

    def reject(self, robot: str | None, key: str, message: str, at: int) -> None:
        """Bad input from the ROS 2 front door: an Event, nothing else."""
        svc = self.svc
        if robot is None:
            # No robot (a namespace that is no robot id, a grid not imported): every instance's
            # front door reads the key, so one reports it, an Event an interval per topic (the
            # topics subscribed: a few), as for JSON keys (names are a client's to invent).
            if svc.ownership.ready and svc.membership.owns_key(key):
                svc.stats.add("received")
                svc.stats.add("rejected")
                topic = key.rsplit("/", 3)[-3] if key.count("/") >= 3 else ""
                code = EventCode.INVALID_KEY
                svc.keywatch.limited(f"ros2_{topic}", "error", code, key, message, at)
            return
        if not svc.ownership.owns(robot):
            return  # its owner reports it
        svc.stats.add("received")
        svc.stats.add("rejected")
        # An initial pose (RViz's "2D Pose Estimate") is an operator's request, said each time.
        dk = names.parse_data_key(key, svc.settings.ros2.domain_id)
        posed = "/" + svc.settings.ros2.initialpose_topic.strip("/")
        kind = "initialpose" if dk is not None and dk.topic.endswith(posed) else None
        self._invalid(robot, kind, key, message, at)

    def _invalid(self, robot: str, kind: str | None, key: str, message: str, at: int) -> None:
        """An Event ``invalid_message`` for a rejected input of ``robot``: at most one per
        ``event_interval_s`` for a robot's scans and odometry, the next counting those held back
        (Health counts every one); an operator's request is answered each time."""
        held = 0 if kind in REQUESTS else self.svc.gate.rejection(robot, "invalid_message", at)
        if held is None:
            return
        more = f" ({held} more like it since the last such Event)" if held else ""
        self.svc._robot_event(robot, "error", EventCode.INVALID_MESSAGE, key, message + more, at)
