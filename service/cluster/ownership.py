"""The robots one instance localizes, and the handover of a robot to this instance.

The owner of a robot comes from :class:`service.cluster.membership.Membership`. For robots it
does not own, an instance ignores the inputs (not recorded, not counted as received or rejected;
counted as ``ignored_not_owner``) except that it keeps a short tail of their odometry, and it
follows every robot's pose puts, keeping the newest PoseEstimate per robot.

A robot is *acquired* at its first input after this instance became its owner, whether the
instance never held it (first sight, a member left or joined) or held it before and lost it.
Before that input the robot is seeded from its last published pose: the odometry tail (from the
reading at or before the pose's stamp on), then an InitialPose built from that pose (map, x, y,
theta, stamp), so the localizer starts from the pose with odometry anchored at its stamp. (An
operator's InitialPose newer than the last pose, which the old owner never localized from, is
used instead, as it was received.) Both go through the same path as received inputs and are
recorded like them: **handover seeds are recorded as initial poses** on the robot's
``initialpose`` topic (and the tail on its ``odom`` topic), so replaying the instance's log
reproduces the handover. Seeds are never published. A last pose that carries ``hypotheses`` (a
relocalization that had not decided between places) is no place to start from: the seed is then
a Relocalize on its map, recorded on the ``relocalize`` topic, and the new owner decides anew.

After a restart, the poses of the durable state (:mod:`service.cluster.posestate`) are handed
in with :meth:`Ownership.restore`, with the odometry readings around their stamps: the robot is
then seeded as on a handover, and its first live odometry brings the motion it made while the
service was down. A restored pose published longer than ``resume_max_age_ns`` ago is no place to
start from either (the robot may have been carried, or its odometry restarted): the seed is a
Relocalize on the pose's map.

With no pose in memory (every instance restarted, no durable state), the pose is fetched with a
Zenoh get on a thread of its own (a storage on the pose keys answers); the robot's inputs are
held meanwhile (at most :data:`HOLD_MAX` per robot and :data:`HOLD_BYTES` over all robots, the
rest dropped and counted) and released in order after the seed, with receive times taken at
release so the recorded order is the order the engine saw. An input that starts with the
operator's InitialPose needs no seed.

**Exactly one answer per scan when an instance joins.** A joiner owns its robots as soon as it
has declared its token, but their previous owner keeps localizing them until the token reaches
it, and answers the scans it had taken by then: for that moment both would answer the same
scans. So for :attr:`Ownership.grace_until` after the join, the robots a joiner acquires are
held as for a fetch, and seeded when the grace is over from the newest pose then followed (the
previous owner's answers included); a held scan stamped at or before that pose was answered
there and is left out (counted in ``handover_answered_elsewhere``). The same holds for any
acquisition: a scan no newer than the robot's newest pose is not localized again.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from schemas import InitialPose, Odometry, PoseEstimate, Relocalize, SchemaError, decode, encode
from service.cluster.followed import FollowedPoses, superseded
from service.cluster.membership import Membership
from service.keys import MODELS, InputKind, Message

log = logging.getLogger(__name__)

Admit = Callable[[str, InputKind, bytes, Message, int], None]
"""Record and dispatch one input: robot, kind, payload, message, receive time (ns)."""
FetchPose = Callable[[str], PoseEstimate | None]
"""The robot's last pose from the bus, or ``None`` (blocking; called off the Zenoh threads)."""

#: Inputs held per robot while its pose is fetched; later ones are dropped and counted.
HOLD_MAX = 256
#: Bytes of inputs held over every robot at once; inputs past it are dropped and counted.
HOLD_BYTES = 64 * 1024 * 1024
#: Odometry readings kept per robot not owned, whatever their stamps.
TAIL_MAX = 1024
#: Robot ids Health lists at most (``owned_count`` counts them all).
OWNED_LISTED = 50


@dataclass(frozen=True)
class _Odom:
    """A reading kept for a seed; one of a robot owned elsewhere as it came (``message`` None,
    ``stamp_ns`` its receive time), decoded only if a seed needs it (:func:`_decoded`)."""

    stamp_ns: int
    payload: bytes
    message: Odometry | None
    max_bytes: int = 0


class Ownership:
    """Which robots this instance localizes, and their seeding when it acquires them.

    Nothing is owned until :attr:`ready` is set: a starting instance first follows the fleet
    (poses and odometry) so that it can seed the robots it takes over. It installs itself as
    the membership's ``on_change``: when members come or go, the robots that moved away are
    released at once.

    Args:
        membership: the live members and the robot owners.
        admit: records and dispatches an input (see :data:`Admit`).
        clock: strictly increasing receive clock, ns.
        tail_ns: how much odometry (by stamp, before the newest reading) to keep per robot
            owned elsewhere, to anchor a seed at the last pose's stamp.
        on_release: called (lock held, keep it short) when a robot stops being localized here.
        resume_max_age_ns: a pose handed in by :meth:`restore` and published longer ago than
            this when the robot is acquired seeds a relocalization on its map instead.
    """

    def __init__(
        self,
        membership: Membership,
        admit: Admit,
        clock: Callable[[], int],
        tail_ns: int,
        on_release: Callable[[str], None] | None = None,
        resume_max_age_ns: int | None = None,
    ) -> None:
        self.membership = membership
        self._admit = admit
        self._fetch: FetchPose = lambda robot: None
        self.ready = False
        #: Until this time (``time.monotonic``), robots acquired wait for their previous
        #: owner's last answers before their seed (set by a joining instance).
        self.grace_until = 0.0
        self._clock = clock
        self._tail_ns = tail_ns
        self._on_release = on_release or (lambda robot: None)
        self.lock = threading.RLock()
        self._active: set[str] = set()
        self._held: dict[str, list[tuple[InputKind, bytes, Message]]] = {}
        self._held_bytes = 0
        self._last_in: dict[str, int] = {}
        self.followed = FollowedPoses(clock, self.lock)
        self._tails: dict[str, deque[_Odom]] = {}
        self._placed: dict[str, tuple[bytes, InitialPose, int]] = {}  # and when received
        self._max_age_ns = resume_max_age_ns
        self._restored: dict[str, tuple[int, int]] = {}  # robot: pose stamp, published at
        self._fetches: queue.Queue[str | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self.ignored_not_owner = 0
        self.seeded = 0
        self.fetched = 0
        self.held_dropped = 0
        self.answered_elsewhere = 0
        self.resumed = 0
        self.resumed_relocalize = 0
        membership.on_change = self.rebalance

    # ------------------------------------------------------------------------ lifecycle
    def start(self, fetch: FetchPose) -> None:
        """Start the thread that fetches the poses of robots acquired with none in memory."""
        self._fetch = fetch
        self._thread = threading.Thread(target=self._fetcher, name="rlutf-handover", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the pose-fetching thread (a get in progress ends at its timeout)."""
        self._fetches.put(None)
        if self._thread is not None:
            self._thread.join(timeout)

    # ------------------------------------------------------------------------ followers
    def follow_pose(self, robot: str, payload: bytes, max_bytes: int) -> str | None:
        """Keep a pose put on the bus (by any instance) if it is the robot's newest
        (:meth:`service.cluster.followed.FollowedPoses.follow`: why it was not, if its stamp is
        too far ahead of the clock). A placement followed is superseded by its owner's poses
        on its map put long enough after it (:func:`superseded`)."""
        placed = self._placed.get(robot)
        if placed is not None and superseded(placed[1], placed[2], payload, self._clock()):
            with self.lock:
                if self._placed.get(robot) is placed:
                    del self._placed[robot]
        return self.followed.follow(robot, payload, max_bytes)

    def follow_own_pose(self, robot: str, payload: bytes, stamp_ns: int) -> None:
        """Keep a pose this instance published for ``robot`` if it is the robot's newest
        (encoded, stamped ``stamp_ns``; decoded only if a seed needs it)."""
        self.followed.follow_own(robot, payload, stamp_ns)

    def remember(self, *poses: PoseEstimate) -> None:
        """Keep each robot's pose if it is the newest known (and not stamped in the future)."""
        self.followed.remember(*poses)

    def forget(self, robot: str) -> None:
        """Drop everything held for ``robot`` (evicted: it sent nothing for long)."""
        with self.lock:
            self._active.discard(robot)
            self.followed.forget(robot)
            self._unhold(robot)
            for held in (
                self._last_in,
                self._tails,
                self._placed,
                self._restored,
            ):
                held.pop(robot, None)

    def restore(self, pose: PoseEstimate, odometry: Sequence[Odometry], published_ns: int) -> None:
        """Hand in a robot's pose from the durable state, as read back at start.

        Args:
            pose: the last pose published for the robot before the restart.
            odometry: its readings around the pose's stamp (they anchor the seed).
            published_ns: when the pose was published (service clock), for its age.
        """
        robot = pose.robot_id
        with self.lock:
            self.remember(pose)
            if self.followed.poses.get(robot) is not pose:
                return  # a newer pose is known already (followed on the bus)
            self._restored[robot] = (pose.stamp_ns, published_ns)
            tail = self._tails.setdefault(robot, deque(maxlen=TAIL_MAX))
            for o in odometry:
                tail.append(_Odom(o.stamp_ns, encode(o), o))

    def last_pose(self, robot: str) -> PoseEstimate | None:
        """The newest pose followed for ``robot``."""
        with self.lock:
            return self.followed.newest(robot)

    def owns(self, robot: str) -> bool:
        """Whether this instance owns ``robot`` now (never before :attr:`ready`)."""
        return self.ready and self.membership.owns(robot)

    def ignore(self, robot: str, kind: InputKind, payload: bytes, max_bytes: int) -> None:
        """Count an input of a robot owned elsewhere.

        Odometry goes to the robot's tail; the newest InitialPose is kept too, in case its
        owner dies before localizing a scan from it.
        """
        with self.lock:
            self.ignored_not_owner += 1
            if robot in self._active or robot in self._held:
                self._release(robot)  # moved away just now; rebalance may not have run yet
        if kind in ("scan", "relocalize"):  # a relocalization is its owner's to run
            return
        if kind == "odom":  # kept as it came, decoded if a seed needs it (see _Odom)
            now = self._clock()
            with self.lock:
                tail = self._tails.get(robot)
                if tail is None:
                    if self.followed.full(self._tails):
                        return
                    tail = self._tails[robot] = deque(maxlen=TAIL_MAX)
                tail.append(_Odom(now, bytes(payload), None, max_bytes))
                while tail[0].stamp_ns < now - self._tail_ns:
                    tail.popleft()
            return
        try:
            msg = decode(MODELS[kind], payload, max_bytes=max_bytes)
        except SchemaError:
            return  # its owner reports it
        if isinstance(msg, InitialPose):
            with self.lock:
                placed = self._placed.get(robot)
                if placed is None or msg.stamp_ns >= placed[1].stamp_ns:
                    self._placed[robot] = (bytes(payload), msg, self._clock())

    # ------------------------------------------------------------------------ inputs
    def offer(
        self, robot: str, kind: InputKind, payload: bytes, message: Message, received_ns: int
    ) -> bool:
        """Localize a validated input here if this instance owns its robot.

        Returns:
            ``False`` when the robot is owned elsewhere (the input was ignored and counted).
        """
        with self.lock:
            if not self.owns(robot):
                if robot in self._active or robot in self._held:
                    self._release(robot)
                self.ignored_not_owner += 1
                return False
            if robot in self._active:
                self._pass(robot, kind, payload, message, received_ns)
            elif robot in self._held:
                if len(self._held[robot]) < HOLD_MAX and self._hold(payload):
                    self._held[robot].append((kind, payload, message))
                    if kind == "initialpose" and not self._in_grace():
                        # the operator places it: no need to wait for its pose on the bus,
                        # behind the lookups of every new id before it (a flood's)
                        self._fetched(robot, None)
                else:
                    self.held_dropped += 1
            else:
                self._acquire(robot, kind, payload, message, received_ns)
            return True

    def _pass(
        self, robot: str, kind: InputKind, payload: bytes, message: Message, received_ns: int
    ) -> None:
        # A receive time taken before a seed or a release of held inputs would sort this input
        # before them in the log; take a new one then.
        if received_ns <= self._last_in.get(robot, 0):
            received_ns = self._clock()
        self._last_in[robot] = received_ns
        self._admit(robot, kind, payload, message, received_ns)

    def _acquire(
        self, robot: str, kind: InputKind, payload: bytes, message: Message, received_ns: int
    ) -> None:
        if kind == "initialpose":  # the operator places it: nothing to seed
            self._placed.pop(robot, None)
            self._seed(robot, message.stamp_ns, None)
        elif self._has_seed(robot) and not self._in_grace():
            pose = self.followed.newest(robot)
            self._start_from(robot, pose)
            if kind == "scan" and _answered(message, pose):
                self.answered_elsewhere += 1
                return
        elif self._hold(payload):  # while the pose is fetched, or the grace (see the module)
            self._held[robot] = [(kind, payload, message)]
            self._fetches.put(robot)
            return
        else:  # over the bytes held: not acquired yet (its next input tries again)
            self.held_dropped += 1
            return
        self._pass(robot, kind, payload, message, received_ns)

    def _in_grace(self) -> bool:
        return time.monotonic() < self.grace_until

    def _has_seed(self, robot: str) -> bool:
        """Whether a pose or an operator's placement is known to seed ``robot`` from."""
        return self.followed.holds(robot) or robot in self._placed

    def _hold(self, payload: bytes) -> bool:
        """Count ``payload`` as held if the bytes held stay within :data:`HOLD_BYTES`."""
        if self._held_bytes + len(payload) > HOLD_BYTES:
            return False
        self._held_bytes += len(payload)
        return True

    def _unhold(self, robot: str) -> list[tuple[InputKind, bytes, Message]] | None:
        """The inputs held for ``robot``, no longer held."""
        held = self._held.pop(robot, None)
        if held is not None:
            self._held_bytes -= sum(len(payload) for _, payload, _ in held)
        return held

    def _start_from(self, robot: str, pose: PoseEstimate | None) -> None:
        placed = self._placed.pop(robot, None)
        restored = self._restored.pop(robot, None)
        if pose is not None and restored is not None and restored[0] == pose.stamp_ns:
            self.resumed += 1  # the seed below is the pose from before the restart
            age_ns = self._clock() - restored[1]
            log.info("%s: resumed from the pose published %.1f s ago", robot, age_ns / 1e9)
            if placed is None and self._max_age_ns is not None and age_ns > self._max_age_ns:
                self.resumed_relocalize += 1
                again = Relocalize(stamp_ns=pose.stamp_ns, map_id=pose.map_id)
                self._seed(robot, pose.stamp_ns, (encode(again), again))
                return
        if placed is not None and (pose is None or placed[1].stamp_ns > pose.stamp_ns):
            self._seed(robot, placed[1].stamp_ns, placed[:2])  # placed, not localized since
        elif pose is not None and pose.hypotheses:  # ambiguous: its best guess may be wrong
            again = Relocalize(stamp_ns=pose.stamp_ns, map_id=pose.map_id)
            self._seed(robot, pose.stamp_ns, (encode(again), again))
        elif pose is not None:
            seed = InitialPose(
                stamp_ns=pose.stamp_ns, map_id=pose.map_id, x=pose.x, y=pose.y, theta=pose.theta
            )
            self._seed(robot, pose.stamp_ns, (encode(seed), seed))
        else:
            self._seed(robot, None, None)

    def _seed(
        self,
        robot: str,
        anchor_ns: int | None,
        seed: tuple[bytes, InitialPose | Relocalize] | None,
    ) -> None:
        """Hand the odometry tail and the seed to the engine; the robot is localized here."""
        tail = sorted(_decoded(self._tails.pop(robot, ())), key=lambda o: o.stamp_ns)
        if anchor_ns is not None:
            before = [i for i, o in enumerate(tail) if o.stamp_ns <= anchor_ns]
            tail = tail[before[-1] :] if before else tail
        for o in tail:
            assert o.message is not None
            self._pass(robot, "odom", o.payload, o.message, self._clock())
        self._active.add(robot)
        if seed is not None:
            kind: InputKind = "relocalize" if isinstance(seed[1], Relocalize) else "initialpose"
            self._pass(robot, kind, seed[0], seed[1], self._clock())
            self.seeded += 1
            log.info("%s: seeded from its pose at %d", robot, seed[1].stamp_ns)

    def _fetcher(self) -> None:
        while True:
            robot = self._fetches.get()
            if robot is None:
                return
            wait = self.grace_until - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            with self.lock:
                if robot not in self._held:
                    continue  # placed, released or evicted meanwhile: nothing to look up
                known = self._has_seed(robot)
            try:
                found = None if known else self._fetch(robot)
            except Exception:
                log.exception("fetching the pose of %s failed", robot)
                found = None
            self._fetched(robot, found)

    def _fetched(self, robot: str, found: PoseEstimate | None) -> None:
        with self.lock:
            held = self._unhold(robot)
            if held is None:
                return  # released meanwhile
            self.fetched += found is not None
            pose = self.followed.newest(robot)
            if found is not None and (pose is None or found.stamp_ns > pose.stamp_ns):
                pose = self.followed.poses[robot] = found
            first_kind, _, first = held[0]
            if first_kind == "initialpose":
                self._placed.pop(robot, None)
                self._seed(robot, first.stamp_ns, None)
            else:
                # The odometry held goes with the tail, before the seed: the seed's stamp may
                # be later than some of it (the previous owner answered scans meanwhile).
                tail = self._tails.setdefault(robot, deque(maxlen=TAIL_MAX))
                tail.extend(_Odom(m.stamp_ns, p, m) for _, p, m in held if isinstance(m, Odometry))
                held = [h for h in held if not isinstance(h[2], Odometry)]
                self._start_from(robot, pose)
            for kind, payload, message in held:
                if kind == "scan" and _answered(message, pose):
                    self.answered_elsewhere += 1
                    continue
                self._pass(robot, kind, payload, message, self._clock())

    # ------------------------------------------------------------------------ membership
    def rebalance(self) -> None:
        """Stop localizing the robots this instance no longer owns (membership changed)."""
        with self.lock:
            for robot in [*self._active, *self._held]:
                if not self.membership.owns(robot):
                    self._release(robot)

    def _release(self, robot: str) -> None:
        self._active.discard(robot)
        self.ignored_not_owner += len(self._unhold(robot) or ())
        self._on_release(robot)
        log.info("%s: now owned by %s", robot, self.membership.owner(robot))

    def acquiring(self) -> int:
        """Robots whose inputs wait for their pose to be fetched."""
        with self.lock:
            return len(self._held)

    def holds(self, robot: str) -> bool:
        """Whether ``robot`` is localized here or waits for its seed."""
        with self.lock:
            return robot in self._active or robot in self._held

    def active(self, robot: str) -> bool:
        """Whether ``robot`` is localized here (owned and seeded)."""
        with self.lock:
            return robot in self._active

    def owned(self) -> list[str]:
        """Robots localized here, sorted."""
        with self.lock:
            return sorted(self._active)

    def figures(self) -> dict[str, object]:
        """Scale-out figures for the health message."""
        members = self.membership.members
        with self.lock:
            return {
                "members": len(members),
                "member_names": members,
                # A summary: a few ids, not thousands (the robots view lists them all).
                "owned": sorted(self._active)[:OWNED_LISTED],
                "owned_count": len(self._active),
                "acquiring": len(self._held),
                "ignored_not_owner": self.ignored_not_owner,
                "handover_seeds": self.seeded,
                "handover_fetched": self.fetched,
                "handover_held_dropped": self.held_dropped,
                "handover_answered_elsewhere": self.answered_elsewhere,
                "resumed": self.resumed,
                "resumed_relocalize": self.resumed_relocalize,
                "poses_rejected": self.followed.rejected,
            }


def _answered(scan: Message, pose: PoseEstimate | None) -> bool:
    """Whether ``pose`` (the robot's newest, from any instance) answers ``scan`` already."""
    return pose is not None and scan.stamp_ns <= pose.stamp_ns


def _decoded(tail: Iterable[_Odom]) -> list[_Odom]:
    """A tail's readings decoded, with their own stamps (undecodable ones left out)."""
    out = []
    for o in tail:
        try:
            msg = o.message or decode(Odometry, o.payload, max_bytes=o.max_bytes)
        except SchemaError:
            continue  # its robot's owner reported it
        out.append(_Odom(msg.stamp_ns, o.payload, msg))
    return out
