"""The newest pose of every robot, followed on the bus, for the seed of a robot handed over.

Every instance follows every robot's pose puts (:class:`service.cluster.ownership.Ownership`
seeds a robot it acquires from the robot's last pose). A pose is kept by its stamp: the newest
stays, and one stamped further ahead of the service's clock than ``max_stamp_ahead_s`` is not
followed (a forged far-future pose would otherwise be every later seed).

Most poses are never used: a robot is handed over rarely, and its pose changes ten times a
second. So a pose as this service encodes it (:func:`schemas.fastpose.encode_pose`: the stamp
and the robot id first), this instance's own as the engine wrote it and every other instance's
as it came, is kept as bytes and decoded only when a seed needs it; other encodings (another
tool's PoseEstimate, fields in another order) are decoded when they arrive.
"""

from __future__ import annotations

import heapq
import logging
import threading
from collections.abc import Callable, Mapping

from schemas import InitialPose, PoseEstimate, SchemaError, decode
from schemas.fastpose import read_head

log = logging.getLogger(__name__)

#: A robot's pose put this long after an InitialPose of it was received answers a scan its owner
#: handled after the InitialPose, whatever their stamps say, ns.
PLACED_NS = 2_000_000_000


def superseded(placed: InitialPose, received_ns: int, pose: bytes, now_ns: int) -> bool:
    """Whether a robot's pose put at ``now_ns`` (encoded) supersedes the robot's InitialPose
    received at ``received_ns``, as the seed of a handover: on its map, put more than
    :data:`PLACED_NS` after it. Stamps alone cannot say: an operator's clock (the InitialPose's)
    and the robot's (its scans', so its poses') may be years apart, and a robot whose clock is
    behind was seeded, at every handover, from the InitialPose it was placed with long before.
    """
    on_map = b'"map_id":"%s"' % placed.map_id.encode()
    return now_ns - received_ns > PLACED_NS and on_map in pose


class FollowedPoses:
    """The newest pose followed per robot (decoded, or kept as encoded until a seed needs it).

    Args:
        clock: the service's receive clock, ns.
        lock: the lock its owner holds around it (every method takes it).
    """

    def __init__(self, clock: Callable[[], int], lock: threading.RLock) -> None:
        self._clock = clock
        self.lock = lock
        self.poses: dict[str, PoseEstimate] = {}
        # Poses kept as they were encoded: stamp, payload, whether this instance encoded it. A
        # robot is in poses or in encoded, never in both.
        self.encoded: dict[str, tuple[int, bytes, bool]] = {}
        self.rejected = 0
        self.replaced = 0  # poses dropped for a newer robot's, max_robots held
        self._ages: list[tuple[int, str]] = []  # (stamp, robot) of poses kept, some stale
        #: Poses stamped further ahead of the clock are not followed (None: no bound).
        self.max_ahead_ns: int | None = None
        #: Robots whose poses are followed at most (others' are ignored).
        self.max_robots: int | None = None

    def follow(self, robot: str, payload: bytes, max_bytes: int) -> str | None:
        """Keep a pose put on the bus (by any instance) if it is the robot's newest.

        Returns:
            Why the pose was rejected when its stamp is too far ahead of the clock, else
            ``None`` (kept, older than the one held, or not a pose of ``robot``).
        """
        if len(payload) > max_bytes:
            return None
        head = read_head(payload)
        if head is not None and head[1] == robot:
            stamp_ns = head[0]
            if self._ahead(stamp_ns):
                return _too_far_ahead(stamp_ns - self._clock())
            self._keep_encoded(robot, stamp_ns, payload, mine=False)
            return None
        try:
            pose = decode(PoseEstimate, payload, max_bytes=max_bytes)
        except SchemaError:
            return None
        if pose.robot_id != robot:
            return None
        if self._ahead(pose.stamp_ns):
            return _too_far_ahead(pose.stamp_ns - self._clock())
        self.remember(pose)
        return None

    def follow_own(self, robot: str, payload: bytes, stamp_ns: int) -> None:
        """Keep a pose this instance published for ``robot`` (``payload`` as the engine encoded
        it, stamped ``stamp_ns``) if it is the robot's newest, without decoding it."""
        if not self._ahead(stamp_ns):
            self._keep_encoded(robot, stamp_ns, payload, mine=True)

    def _ahead(self, stamp_ns: int) -> bool:
        """Whether a pose so stamped is too far ahead of the clock (and counted if so)."""
        if self.max_ahead_ns is None or stamp_ns - self._clock() <= self.max_ahead_ns:
            return False
        with self.lock:
            self.rejected += 1
        return True

    def _keep_encoded(self, robot: str, stamp_ns: int, payload: bytes, mine: bool) -> None:
        with self.lock:
            kept = self.encoded.get(robot)
            held = self.poses.get(robot) if kept is None else None
            if kept is None and held is None and not self._room(stamp_ns):
                return
            if (kept is not None and stamp_ns < kept[0]) or (
                held is not None and stamp_ns < held.stamp_ns
            ):
                return
            if held is not None:
                del self.poses[robot]
            self.encoded[robot] = (stamp_ns, payload, mine)
            self._aged(robot, stamp_ns)

    def remember(self, *poses: PoseEstimate) -> None:
        """Keep each robot's pose if it is the newest known (and not stamped in the future)."""
        with self.lock:
            for pose in poses:
                robot = pose.robot_id
                kept = self.encoded.get(robot)
                held = self.poses.get(robot)
                if self._ahead(pose.stamp_ns):
                    continue
                if held is None and kept is None and not self._room(pose.stamp_ns):
                    continue
                newest = (
                    kept[0] if kept is not None else held.stamp_ns if held is not None else None
                )
                if newest is None or pose.stamp_ns >= newest:
                    self.encoded.pop(robot, None)
                    self.poses[robot] = pose
                    self._aged(robot, pose.stamp_ns)

    def _room(self, stamp_ns: int) -> bool:
        """Whether a new robot's pose stamped ``stamp_ns`` may be kept (under the lock): below
        :attr:`max_robots`, or in place of the stalest pose held if that one is older. Poses of
        made-up robot ids (any client may put poses) were kept for good once
        :attr:`max_robots` were held, and no real robot's pose was followed from then on: a
        robot handed over then had no seed. Now such poses give way as they age."""
        if not self.full(self.poses, len(self.encoded)):
            return True
        ages = self._ages
        while ages:
            stamp, robot = ages[0]
            if self._stamp(robot) != stamp:  # an older entry of a robot's (or one forgotten)
                heapq.heappop(ages)
                continue
            if stamp >= stamp_ns:
                return False
            heapq.heappop(ages)
            self.poses.pop(robot, None)
            self.encoded.pop(robot, None)
            self.replaced += 1
            return True
        return False

    def _stamp(self, robot: str) -> int | None:
        kept = self.encoded.get(robot)
        if kept is not None:
            return kept[0]
        pose = self.poses.get(robot)
        return None if pose is None else pose.stamp_ns

    def _aged(self, robot: str, stamp_ns: int) -> None:
        """Note a pose kept (under the lock): the heap of stamps the stalest is found in, kept
        within a few times the poses held."""
        held = len(self.poses) + len(self.encoded)
        if len(self._ages) > 4 * held + 64:
            ages = []
            for r in (*self.poses, *self.encoded):
                stamp = self._stamp(r)
                if stamp is not None:
                    ages.append((stamp, r))
            heapq.heapify(ages)
            self._ages = ages
        heapq.heappush(self._ages, (stamp_ns, robot))

    def full(self, held: Mapping[str, object], more: int = 0) -> bool:
        """Whether ``held`` (with ``more``) is at :attr:`max_robots`."""
        return self.max_robots is not None and len(held) + more >= self.max_robots

    def holds(self, robot: str) -> bool:
        """Whether a pose of ``robot`` is held."""
        return robot in self.poses or robot in self.encoded

    def newest(self, robot: str) -> PoseEstimate | None:
        """The newest pose followed for ``robot``, decoded (and kept so) if it was encoded.

        A pose of another instance whose head was this service's and whose rest does not
        decode (or names another stamp or robot) is no seed: ``None``, with a warning.
        """
        with self.lock:
            kept = self.encoded.pop(robot, None)
            if kept is None:
                return self.poses.get(robot)
            stamp_ns, payload, mine = kept
            try:
                pose = decode(PoseEstimate, payload, max_bytes=len(payload))
            except SchemaError as err:
                if mine:  # the engine's own encoding: only a bug gets here
                    log.exception("%s: its last pose is unreadable", robot)
                else:
                    log.warning(
                        "%s: the last pose followed on the bus is unreadable: %s", robot, err
                    )
                return None
            if pose.robot_id != robot or pose.stamp_ns != stamp_ns:
                log.warning("%s: the last pose followed on the bus contradicts its head", robot)
                return None
            self.poses[robot] = pose
            return pose

    def forget(self, robot: str) -> None:
        """Drop the pose held for ``robot``."""
        with self.lock:
            self.poses.pop(robot, None)
            self.encoded.pop(robot, None)


def _too_far_ahead(ahead_ns: int) -> str:
    """Why a pose stamped ``ahead_ns`` ahead of the clock is not followed."""
    return (
        f"pose stamped {ahead_ns / 1e9:.3g} s ahead of the service's clock not followed: a seed "
        "comes only from a pose stamped no later than now (max_stamp_ahead_s)"
    )
