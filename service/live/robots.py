"""The per-robot view of an instance: ``{prefix}/service/{instance}/robots``, and its client.

The service keeps the latest PoseEstimate payload of every robot it holds; per published pose,
:meth:`RobotView.published` adds only when it was published and the scan's latency (one small
tuple in a dict). The payloads are decoded when someone asks, not per pose.

The answer is a :class:`~schemas.answers.RobotsAnswer` (docs/wire.md, RobotsAnswer): every
robot held with its latest pose and, up to :data:`MAX_WAITING` (the longest silent forgotten
first), the robots that send scans but have no pose yet (no initial pose, or a map not loaded),
aged from the latest such scan's Event, and those given an initial pose that have sent no scan
since (``no_scan_yet``, aged from the initial pose). A robot never placed (``not_initialized``)
is listed only while its scans keep coming (:data:`UNPLACED_SHOWN_NS`): an id made up for one
message, a flood of them, is not listed for ``robot_idle_s``.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import NamedTuple

import zenoh

from schemas import (
    PoseEstimate,
    RobotsAnswer,
    RobotState,
    SchemaError,
    WaitingRobot,
    decode,
    encode,
    encode_answer,
)
from service.keys import NO_RETURNS_MESSAGE, Keys

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON


def robots_key(prefix: str, instance: str) -> str:
    """The key of an instance's robot view (``*`` for every instance)."""
    return f"{prefix}/service/{instance}/robots"


def one_sigma(covariance: Sequence[float] | None) -> tuple[float | None, float | None]:
    """1-sigma uncertainty of a row-major 3x3 covariance (x, y, theta): the larger semi-axis of
    the position's 1-sigma ellipse (metres) and the heading's (radians); ``None`` without one."""
    if covariance is None or len(covariance) != 9:
        return None, None
    xx, xy, yy, tt = covariance[0], covariance[1], covariance[4], covariance[8]
    half = (xx + yy) / 2
    largest = half + math.sqrt(max(((xx - yy) / 2) ** 2 + xy * xy, 0.0))
    return _finite(math.sqrt(max(largest, 0.0))), _finite(math.sqrt(max(tt, 0.0)))


def _finite(value: float) -> float | None:
    """``value``, or ``None`` for an infinity (variances near the end of the float range
    overflow): RobotState refuses infinities, and the answer always wrote ``null`` for one."""
    return value if math.isfinite(value) else None


#: How the status lost reads in an encoded PoseEstimate (compact JSON, as :func:`schemas.encode`
#: writes it): counting lost robots needs no decoding.
_LOST = b'"status":"lost"'
#: Events that say a robot sends scans but gets no pose, as their code reads in an Event.
_WAITING = {
    b'"code":"not_initialized"': "not_initialized",
    b'"code":"map_not_found"': "map_not_found",
    b'"code":"stamp_rejected"': "stamp_rejected",
}
#: The reason of a robot given an initial pose that has sent no scan since.
NO_SCAN_YET = "no_scan_yet"
#: The reason of a robot that sends scans but was never given a pose.
NOT_INITIALIZED = "not_initialized"
#: The reason of a robot whose inputs are stamped too far ahead of the service's clock (its
#: clock is ahead): every one is refused, so it gets no pose, although it sends scans.
STAMP_REJECTED = "stamp_rejected"
#: Reasons said again by every ``event_interval_s`` while they hold: forgotten once they stop.
_REPEATED = (NOT_INITIALIZED, STAMP_REJECTED)
#: How long a robot never placed stays listed after its latest ``not_initialized`` Event, ns
#: (at least; three ``event_interval_s`` where that is longer, :attr:`RobotView.unplaced_ns`):
#: one that scans gets such an Event every ``event_interval_s``, while an id made up for a
#: message or a few (10,000 of them in a quarter of a second, made up by a client) stayed listed
#: for ``robot_idle_s`` (an hour), crowding out the robots that do wait.
UNPLACED_SHOWN_NS = 10_000_000_000
#: Inputs that place a robot on a map, after which it is listed (:data:`NO_SCAN_YET`) until its
#: first pose: a Relocalize too (it went unlisted, or stayed "no map" after one on a mistyped
#: map while the robot sent no scans).
PLACING = ("initialpose", "relocalize")
#: The reason of a robot whose scans have too few returns to give a pose (a lidar blocked or
#: failing, range limits that leave nothing): it sends scans, so "no scan yet" would mislead.
NO_RETURNS = "no_returns"
_NO_RETURNS = NO_RETURNS_MESSAGE.encode()  # in an Event's payload as JSON writes it
#: Robots remembered as waiting, at most (the longest silent are forgotten first).
MAX_WAITING = 1000

#: An answer made this recently is given again while no robot came or went, ns: making one
#: decodes every pose held (about 12 us a robot), so a flood of gets makes a few a second.
ANSWER_REUSE_NS = 250_000_000


class _Published(NamedTuple):
    at_ns: int  # when the pose was published (service clock)
    latency_ns: int | None  # scan receipt to publication


class RobotView:
    """Per-robot publication times of one instance, and the answer built from them.

    Args:
        instance: the instance's name (``owner`` of every robot).
        poses: the service's latest PoseEstimate payload per robot it holds (read, not copied).
        clock: the service clock, ns since the epoch.
    """

    def __init__(
        self,
        instance: str,
        poses: Mapping[str, bytes],
        clock: Callable[[], int],
        prefix: str = "rlutf",
    ) -> None:
        self.instance = instance
        self.key = robots_key(prefix, instance)
        self._poses = poses
        self._clock = clock
        self._published: dict[str, _Published] = {}
        # robot -> (when, event code, the map of its initial pose)
        self._waiting: dict[str, tuple[int, str, str | None]] = {}
        self._lock = threading.Lock()  # for the waiting robots only (not the hot path)
        self._keys = Keys(prefix)
        # The poses from before a restart (robot: pose, its payload, when it was published),
        # shown and answered to pose queries for the robots owned here until each one's first.
        self._restored: dict[str, tuple[PoseEstimate, bytes, int]] = {}
        #: Whether this instance owns a robot (:meth:`Ownership.owns`).
        self.owns: Callable[[str], bool] = lambda robot: True
        self._answer: tuple[int, int, bytes] | None = None  # the last answer: when, generation
        self._generation = 0  # counts robots coming and going (a new first pose, a forget)
        #: How long a robot never placed is listed after its latest not_initialized Event, ns.
        self.unplaced_ns = UNPLACED_SHOWN_NS

    # ------------------------------------------------------------------ hot path
    def published(self, robot: str, at_ns: int, received_ns: int | None) -> None:
        """A pose of ``robot`` was published at ``at_ns`` for a scan received at ``received_ns``."""
        # One assignment: a dict store is atomic under the GIL, so no lock.
        if robot not in self._published:
            self._generation += 1
        self._published[robot] = _Published(
            at_ns, None if received_ns is None else at_ns - received_ns
        )

    def event(self, robot: str, payload: bytes, at_ns: int) -> None:
        """An Event about ``robot`` was published at ``at_ns``: remembers a robot whose scans get
        no pose (rate-limited Events, so not per scan)."""
        for code, reason in _WAITING.items():
            if code in payload:
                self._remember(robot, at_ns, reason)
                return
        if _NO_RETURNS in payload and robot not in self._poses:
            self._remember(robot, at_ns, NO_RETURNS)

    def told(self, robot: str, code: str, at_ns: int) -> None:
        """A robot Event ``code`` went out at ``at_ns`` from outside an update (a map no
        storage has, for an InitialPose): a reason the robot waits, as :meth:`event` finds."""
        if code in _WAITING.values():  # the reasons are the codes
            self._remember(robot, at_ns, code)

    def initialized(self, robot: str, at_ns: int, map_id: str | None = None) -> None:
        """An InitialPose of ``robot`` was taken in at ``at_ns``: until its first pose the robot
        is listed as waiting for a scan (:data:`NO_SCAN_YET`), so that a robot given a pose
        before it sends scans is not missing from the view (a refusal's Event, such as
        ``map_not_found``, then gives the reason instead). ``map_id``: the pose's map, shown
        while the robot waits."""
        if robot not in self._poses:
            self._remember(robot, at_ns, NO_SCAN_YET, map_id)

    def _remember(self, robot: str, at_ns: int, reason: str, map_id: str | None = None) -> None:
        self._generation += 1
        with self._lock:
            # Re-inserted last (the freshest at the end), keeping the initial pose's map.
            old = self._waiting.pop(robot, None)
            if map_id is None and old is not None:
                map_id = old[2]
            self._waiting[robot] = (at_ns, reason, map_id)
            while len(self._waiting) > MAX_WAITING:
                del self._waiting[next(iter(self._waiting))]

    def forget(self, robot: str) -> None:
        """``robot`` is no longer held here (moved to another instance)."""
        self._generation += 1
        self._published.pop(robot, None)
        self._restored.pop(robot, None)
        with self._lock:
            self._waiting.pop(robot, None)

    # ------------------------------------------------------------------ scrape and query time
    def held(self) -> int:
        """Robots with a latest pose held."""
        return len(self._poses)

    def lost(self) -> int:
        """Robots held whose latest pose has status lost."""
        return sum(_LOST in payload for payload in list(self._poses.values()))

    def states(self) -> list[RobotState]:
        """Every robot held, by robot id (its latest pose decoded now), with those restored
        after a restart that have sent nothing since (aged from the pose's publication)."""
        now = self._clock()
        out: list[RobotState] = []
        # sorted() copies the items in C, under the GIL: safe while poses are published.
        for robot, payload in sorted(self._poses.items()):
            try:
                pose = decode(PoseEstimate, payload)
            except SchemaError:  # our own output: cannot happen unless the wire model changed
                log.warning("robot view: undecodable pose of %s", robot, exc_info=True)
                continue
            seen = self._published.get(robot)
            age = latency = None
            if seen is not None:
                age = max(now - seen.at_ns, 0) / 1e9
                latency = None if seen.latency_ns is None else seen.latency_ns / 1e6
            state = self._state(pose, age, latency)
            if seen is not None and self._refused(robot, seen.at_ns, now):
                state = state.model_copy(update={"refused": STAMP_REJECTED})
            out.append(state)
        out += [
            self._state(pose, max(now - published, 0) / 1e9, None)
            for pose, _, published in self._restored_here()
        ]
        return sorted(out, key=lambda s: s.robot_id)

    def _refused(self, robot: str, published_ns: int, now: int) -> bool:
        """Whether the robot's inputs have been refused for their stamps since its latest pose
        (published at ``published_ns``), and lately: it sends, but gets no pose."""
        refused = self._waiting.get(robot)
        return (
            refused is not None
            and refused[1] == STAMP_REJECTED
            and published_ns < refused[0]
            and now - refused[0] <= self.unplaced_ns
        )

    def restore(self, pose: PoseEstimate, published_ns: int) -> None:
        """A robot's pose from before a restart, published at ``published_ns``."""
        self._restored[pose.robot_id] = (pose, encode(pose), published_ns)
        self._generation += 1

    def _restored_here(self) -> list[tuple[PoseEstimate, bytes, int]]:
        return [
            entry
            for robot, entry in sorted(self._restored.items())
            if robot not in self._poses and self.owns(robot)
        ]

    def _state(self, pose: PoseEstimate, age: float | None, latency: float | None) -> RobotState:
        sigma_xy, sigma_theta = one_sigma(pose.covariance)
        return RobotState(
            robot_id=pose.robot_id,
            map_id=pose.map_id,
            status=pose.status,
            x=pose.x,
            y=pose.y,
            theta=pose.theta,
            age_s=age,
            latency_ms=latency,
            owner=self.instance,
            localization_score=pose.localization_score,
            deviation_range=pose.deviation_range,
            sigma_xy_m=sigma_xy,
            sigma_theta_rad=sigma_theta,
        )

    def on_pose_query(self, query: zenoh.Query) -> None:
        """The pose queryable's callback (``{prefix}/robots/*/pose``): each robot's latest
        pose held here, a restored one included."""
        with query:
            ke = query.key_expr
            held = list(self._poses.items())
            held += [(pose.robot_id, payload) for pose, payload, _ in self._restored_here()]
            for robot, payload in held:
                key = self._keys.pose(robot)
                if ke.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, payload, encoding=JSON)

    def waiting(self) -> list[WaitingRobot]:
        """Robots whose scans get no pose, by robot id (those with a pose since left out)."""
        now = self._clock()
        with self._lock:  # the robots never placed that went silent are forgotten
            gone = [
                robot
                for robot, (at, reason, _) in self._waiting.items()
                if reason in _REPEATED and now - at > self.unplaced_ns
            ]
            for robot in gone:
                del self._waiting[robot]
        self._generation += bool(gone)
        return [
            WaitingRobot(
                robot_id=robot,
                reason=reason,
                age_s=max(now - at, 0) / 1e9,
                owner=self.instance,
                map_id=map_id,
            )
            for robot, (at, reason, map_id) in sorted(self._waiting.items())
            if robot not in self._poses
        ]

    def answer(self) -> bytes:
        """The encoded :class:`RobotsAnswer` of this instance (the one made less than
        :data:`ANSWER_REUSE_NS` before if no robot came or went since: its ``stamp_ns`` says
        when)."""
        now, generation = self._clock(), self._generation
        last = self._answer
        if last is not None and last[1] == generation and 0 <= now - last[0] < ANSWER_REUSE_NS:
            return last[2]
        made = encode_answer(
            RobotsAnswer(
                instance=self.instance,
                stamp_ns=now,
                robots=tuple(self.states()),
                waiting=tuple(self.waiting()),
            )
        )
        self._answer = (now, generation, made)
        return made

    def on_query(self, query: zenoh.Query) -> None:
        """The queryable's callback: answer on the instance's key (not the query's: a get
        consolidates the replies on one key into one, and ``{prefix}/service/*/robots`` would
        then hear a single instance of several)."""
        with query:
            query.reply(self.key, self.answer(), encoding=JSON)


# ---------------------------------------------------------------------------------- client
def fetch_robots(session: zenoh.Session, prefix: str, timeout: float) -> list[RobotsAnswer]:
    """Every instance's answer on ``{prefix}/service/*/robots`` (undecodable ones skipped)."""
    answers: list[RobotsAnswer] = []
    for reply in session.get(robots_key(prefix, "*"), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            answers.append(RobotsAnswer.model_validate_json(reply.ok.payload.to_bytes()))
        except ValueError:
            log.warning("bad robots answer on %s", reply.ok.key_expr)
    return answers


def merge_robots(answers: Iterable[RobotsAnswer]) -> list[RobotState]:
    """All instances' robots by robot id; a robot two instances hold (during a handover) is
    given once, by the instance that published its pose most recently."""
    best: dict[str, RobotState] = {}
    for answer in answers:
        for state in answer.robots:
            old = best.get(state.robot_id)
            if old is None or _fresher(state, old):
                best[state.robot_id] = state
    return [best[r] for r in sorted(best)]


def _fresher(a: RobotState, b: RobotState) -> bool:
    if a.age_s is None:
        return False
    return b.age_s is None or a.age_s < b.age_s


def merge_waiting(answers: Iterable[RobotsAnswer]) -> list[WaitingRobot]:
    """All instances' waiting robots by robot id, the freshest of each; a robot some instance
    holds a pose of is left out."""
    answers = list(answers)
    posed = {s.robot_id for a in answers for s in a.robots}
    best: dict[str, WaitingRobot] = {}
    for answer in answers:
        for w in answer.waiting:
            old = best.get(w.robot_id)
            if w.robot_id not in posed and (old is None or w.age_s < old.age_s):
                best[w.robot_id] = w
    return [best[r] for r in sorted(best)]
