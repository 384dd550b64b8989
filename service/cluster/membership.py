"""Scale-out: which live instance localizes which robot.

Instances find each other through their liveliness tokens (``{prefix}/service/{instance}``,
WIRE.md); Zenoh carries everything, there is no cluster protocol of our own. Each robot is owned
by exactly one live instance, chosen by rendezvous (highest-random-weight) hashing of the robot
id over the live instance names: every instance computes the same owner from the same
membership, and when a member leaves only that member's robots move (when one joins, only the
robots it wins). A single instance owns every robot, so it behaves as if this module did not
exist.

This module holds the pure assignment, the live membership and the pose gets a handover needs;
:mod:`service.cluster.ownership` applies them to one instance's inputs.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from schemas import PoseEstimate, SchemaError, decode, valid_id
from service.keys import Keys

log = logging.getLogger(__name__)

#: Robots whose owner is remembered at most (then the memo starts anew). Each made-up robot id
#: of a flood was remembered until the members next changed: 100 bytes an id, without end.
OWNERS_MAX = 65_536


def rendezvous_weight(member: str, robot: str) -> int:
    """The weight of ``member`` for ``robot``: a stable 64-bit hash of both names.

    Stable across processes, hosts and Python versions (BLAKE2b, not :func:`hash`), so every
    instance ranks the members the same way.
    """
    digest = hashlib.blake2b(f"{member}\x00{robot}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def owner_of(robot: str, members: Iterable[str]) -> str | None:
    """The member with the highest rendezvous weight for ``robot``; ``None`` with no members.

    Ties (64-bit collisions) go to the greatest name, so the choice is total.
    """
    return max(members, key=lambda m: (rendezvous_weight(m, robot), m), default=None)


def assign(robots: Iterable[str], members: Iterable[str]) -> dict[str, str]:
    """Owner of every robot.

    Raises:
        ValueError: there are no members.
    """
    alive = sorted(set(members))
    if not alive:
        raise ValueError("no live member to assign robots to")
    return {r: owner_of(r, alive) or alive[0] for r in robots}


class Membership:
    """The live instances of one prefix, from their liveliness tokens.

    The instance itself is always a member of its own view (a partitioned instance keeps
    localizing the robots it can reach rather than none).

    Args:
        instance: this instance's name.
        on_change: called (from a Zenoh thread, keep it short) after the member set changed.
    """

    def __init__(self, instance: str, on_change: Callable[[], None] | None = None) -> None:
        self.instance = instance
        self.on_change = on_change
        self._alive: set[str] = {instance}
        self._heard: set[str] = set()
        self._generation = 0
        self._owners: dict[str, tuple[int, str]] = {}
        self._lock = threading.Lock()
        self._sub: Any = None
        self._head = ""

    def start(self, session: zenoh.Session, keys: Keys, timeout: float) -> None:
        """Learn the live members, then follow their tokens on ``{prefix}/service/*``.

        A liveliness get gives the current members (issued before the subscriber: a get right
        after a liveliness subscriber's declaration was seen to come back empty); the
        subscriber, with history, then reports each of them again and every change. A member of
        the get that the subscriber has not reported within ``timeout`` and that a second get
        does not show either died in between.
        """
        self._head = keys.service("")
        primed = self._tokens(session, keys, timeout) - {self.instance}
        self._sub = session.liveliness().declare_subscriber(
            keys.all_services, self._on_sample, history=True
        )
        for name in primed:
            self.update(name, alive=True, prime=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self._unheard(primed):
            time.sleep(0.005)
        missing = self._unheard(primed)
        if missing:  # ask again before declaring them gone
            for name in missing - self._tokens(session, keys, timeout):
                self.update(name, alive=False)

    def _tokens(self, session: zenoh.Session, keys: Keys, timeout: float) -> set[str]:
        replies = session.liveliness().get(keys.all_services, timeout=timeout)
        return {self._name(str(r.ok.key_expr)) for r in replies if r.ok is not None}

    def _unheard(self, names: set[str]) -> set[str]:
        with self._lock:
            return names - self._heard

    def close(self) -> None:
        """Stop following the tokens."""
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def _name(self, key: str) -> str:
        return key[len(self._head) :] if key.startswith(self._head) else ""

    def _on_sample(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        self.update(self._name(str(sample.key_expr)), alive=alive)

    def update(self, name: str, alive: bool, prime: bool = False) -> bool:
        """Apply one token event; returns whether the member set changed.

        Args:
            name: the instance name.
            alive: whether its token exists.
            prime: from the initial get: ignored for names the subscriber already reported.
        """
        if not valid_id(name):  # no instance has that name: a wildcard token (`*`), a deeper key
            return False
        with self._lock:
            if prime and name in self._heard:
                return False
            if not prime:
                self._heard.add(name)
            if name == self.instance or (name in self._alive) == alive:
                return False
            if alive:
                self._alive.add(name)
            else:
                self._alive.discard(name)
            self._generation += 1
            self._owners.clear()
        log.info("member %s %s", name, "joined" if alive else "left")
        if self.on_change is not None:
            self.on_change()
        return True

    @property
    def members(self) -> list[str]:
        """Live instance names, sorted."""
        with self._lock:
            return sorted(self._alive)

    def owner(self, robot: str) -> str:
        """The instance that owns ``robot`` under the current membership (cached)."""
        with self._lock:
            hit = self._owners.get(robot)
            if hit is not None and hit[0] == self._generation:
                return hit[1]
            found = owner_of(robot, self._alive)
            assert found is not None  # the instance itself is always a member
            if len(self._owners) >= OWNERS_MAX:
                self._owners.clear()
            self._owners[robot] = (self._generation, found)
            return found

    def owns(self, robot: str) -> bool:
        """Whether this instance owns ``robot``."""
        return self.owner(robot) == self.instance

    def owns_key(self, key: str) -> bool:
        """Whether this instance answers for a key naming no valid robot (not cached)."""
        with self._lock:
            return owner_of(key, self._alive) == self.instance


def fetch_poses(
    session: zenoh.Session, keys: Keys, selector: str, timeout: float, max_bytes: int
) -> dict[str, PoseEstimate]:
    """The newest PoseEstimate per robot that queryables and storages answer for ``selector``.

    Replies that do not validate or whose key names another robot are skipped; a failed get
    gives what was answered until then.
    """
    found: dict[str, PoseEstimate] = {}
    try:
        for reply in session.get(selector, timeout=timeout):
            if reply.ok is None:
                continue
            try:
                pose = decode(PoseEstimate, reply.ok.payload.to_bytes(), max_bytes=max_bytes)
            except SchemaError:
                continue
            if str(reply.ok.key_expr) != keys.pose(pose.robot_id):
                continue
            held = found.get(pose.robot_id)
            if held is None or pose.stamp_ns > held.stamp_ns:
                found[pose.robot_id] = pose
    except zenoh.ZError:
        log.warning("pose get on %s failed", selector, exc_info=True)
    return found


def fetch_last_pose(
    session: zenoh.Session, keys: Keys, robot: str, timeout: float, max_bytes: int
) -> PoseEstimate | None:
    """The newest PoseEstimate of ``robot`` on the bus; ``None`` when nobody answers."""
    return fetch_poses(session, keys, keys.pose(robot), timeout, max_bytes).get(robot)
