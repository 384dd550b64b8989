"""Bounds on what the service holds for robots: stamps it trusts, ids it takes, idle robots.

Any number of clients may send anything. What one input costs is bounded by validation; what
the service keeps is bounded here:

- **Stamps.** A message stamped far ahead of the service's clock is rejected: a pose is the
  newest by its stamp, so one far-future stamp (a forged pose on the bus, or a robot's own scan)
  would pin the robot's seed for good.
- **Robot ids.** At most ``max_robots`` robots are held; an input for one more id is refused
  (Event ``robot_limit``, at most one a second) until idle robots are evicted.
- **Idle robots.** A robot that sent nothing for ``robot_idle_s`` is evicted: its mailbox, its
  localizer, its followed pose and its durable state go, with an Event ``robot_evicted``
  (recorded, so replay forgets it at the same point). A robot that comes back starts anew, like
  one never seen: an InitialPose (or its last pose, followed on the bus) places it again.
  A robot never placed (no InitialPose, Relocalize or seed taken in: it has no pose and nothing
  worth keeping) is evicted after :data:`UNPLACED_IDLE_S` already: ids made up for a message or
  a few, a burst of ten thousand, held ``max_robots`` full for ``robot_idle_s`` (an hour) and
  every real new robot was refused meanwhile.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

log = logging.getLogger(__name__)

#: Least time between two ``robot_limit`` Events, ns.
LIMIT_EVENT_INTERVAL_NS = 1_000_000_000
#: Stamp rejections reported per second at most (the others are counted).
EVENTS_PER_S = 10
#: Robots whose last rejection Event the gate remembers: ids can be invented without end, so the
#: memory starts again when full (at worst one more Event for a robot then).
REJECTIONS_KEPT = 8192
#: How often idle robots are looked for, seconds.
SWEEP_INTERVAL_S = 1.0
#: How long a robot never placed may send nothing before it is evicted, seconds (or
#: ``robot_idle_s`` where that is shorter); as long as the per-robot view lists it.
UNPLACED_IDLE_S = 10.0


def eviction_message(idle_s: float, placed: bool) -> str:
    """The ``robot_evicted`` Event's message for a robot idle for ``idle_s``."""
    if not placed:
        return (
            f"no input for {idle_s:g} s and never placed (no InitialPose, no pose): the robot is "
            "forgotten; it starts anew at its next input (publish an InitialPose)"
        )
    return (
        f"no input for {idle_s:g} s (robot_idle_s): the robot's state is dropped; it starts "
        "anew at its next input (publish an InitialPose)"
    )


#: The ``robot_evicted`` Event's message for a robot never placed evicted to make room.
MADE_ROOM = (
    "never placed (no InitialPose, no pose), evicted to make room for a robot placed by an "
    "InitialPose or a Relocalize (max_robots held); it starts anew at its next input"
)


class Holder(Protocol):
    """What the gate needs of the service."""

    def robots_held(self) -> int: ...

    def holds(self, robot: str) -> bool: ...


class Gate:
    """Decides, before any work, whether an input is taken.

    Args:
        clock: the service's receive clock, ns.
        max_ahead_ns: largest accepted lead of a stamp over the clock.
        max_robots: most robots held at once.
        event_interval_ns: least time between two rejection Events of one code for one robot
            (the ``event_interval_s`` setting).
    """

    def __init__(
        self,
        clock: Callable[[], int],
        max_ahead_ns: int,
        max_robots: int,
        event_interval_ns: int = 1_000_000_000,
    ) -> None:
        self._clock = clock
        self.max_ahead_ns = max_ahead_ns
        self.max_robots = max_robots
        self.event_interval_ns = event_interval_ns
        self.stamps_rejected = 0
        self.robots_refused = 0
        self._last_limit_event = -LIMIT_EVENT_INTERVAL_NS
        self._window_ns = 0
        self._window_events = 0
        # (robot, code) -> (stamp of the last Event sent, rejections held back since)
        self._rejections: dict[tuple[str, str], tuple[int, int]] = {}

    def stamp_problem(self, stamp_ns: int, now_ns: int) -> str | None:
        """Why a stamp is not trusted, or ``None``."""
        ahead = stamp_ns - now_ns
        if ahead <= self.max_ahead_ns:
            return None
        self.stamps_rejected += 1
        return (
            f"stamp_ns {stamp_ns} is {ahead / 1e9:.3g} s ahead of the service's clock (at most "
            f"{self.max_ahead_ns / 1e9:g} s accepted: max_stamp_ahead_s); the message is "
            "dropped. Synchronise the robot's clock (chrony, NTP) with the service's host"
        )

    def refuse_new(self, holder: Holder, robot: str, now_ns: int) -> str | None:
        """Why a robot id is refused (the service is full), or ``None``.

        Returns the message of a ``robot_limit`` Event at most once a second; refusals in
        between are only counted.
        """
        if holder.holds(robot) or holder.robots_held() < self.max_robots:
            return None
        self.robots_refused += 1
        if now_ns - self._last_limit_event < LIMIT_EVENT_INTERVAL_NS:
            return ""
        self._last_limit_event = now_ns
        return (
            f"robot {robot!r} refused: this instance holds {self.max_robots} robots "
            f"(max_robots); {self.robots_refused} inputs of new robot ids refused so far. Idle "
            "robots are evicted after robot_idle_s; raise max_robots or add instances"
        )

    def allow_event(self, now_ns: int) -> bool:
        """Whether a rejection may be reported now: at most :data:`EVENTS_PER_S` a second
        (a flood of forged messages must not become a flood of Events and log records)."""
        if now_ns - self._window_ns >= 1_000_000_000:
            self._window_ns, self._window_events = now_ns, 0
        self._window_events += 1
        return self._window_events <= EVENTS_PER_S

    def rejection(self, robot: str, code: str, now_ns: int) -> int | None:
        """Whether a rejection Event of ``code`` for ``robot`` goes out now: at most one per
        ``event_interval_ns``, as the engine holds back its own Events (a robot, or anyone
        writing on its keys, sending malformed messages must not become an Event and a record
        of the service's log per message). Returns ``None`` when it is held back (counted), else
        how many were held back since the last one went out."""
        key = (robot, code)
        last = self._rejections.get(key)
        if last is not None and now_ns - last[0] < self.event_interval_ns:
            self._rejections[key] = (last[0], last[1] + 1)
            return None
        if last is None and len(self._rejections) >= REJECTIONS_KEPT:
            self._rejections.clear()
        self._rejections[key] = (now_ns, 0)
        return 0 if last is None else last[1]

    def figures(self) -> dict[str, object]:
        """Figures for the health message."""
        return {"stamps_rejected": self.stamps_rejected, "robots_refused": self.robots_refused}


class Sweeper:
    """A thread that evicts robots idle for longer than ``idle_ns``, and those never placed
    idle for longer than ``unplaced_ns``.

    Args:
        clock: the service's receive clock, ns.
        idle_ns: how long a robot may send nothing.
        idle_since: the robots whose last input was received before a given time (with a
            second argument false: only those never placed).
        evict: evicts one robot, with the message of its Event; returns ``False`` when it is
            busy after all (kept for now).
        unplaced_ns: how long a robot never placed may send nothing (at most ``idle_ns``).
    """

    def __init__(
        self,
        clock: Callable[[], int],
        idle_ns: int,
        idle_since: Callable[[int, bool], list[str]],
        evict: Callable[[str, str], bool],
        unplaced_ns: int = int(UNPLACED_IDLE_S * 1e9),
    ) -> None:
        self._clock = clock
        self._idle_ns = idle_ns
        self.unplaced_ns = min(unplaced_ns, idle_ns)
        self._idle_since = idle_since
        self._evict = evict
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.evicted = 0
        #: Called after each sweep, on the sweeper's thread (the Events a budget held back).
        self.also: Callable[[], None] = lambda: None

    def start(self) -> None:
        """Start sweeping."""
        self._thread = threading.Thread(target=self._run, name="rlutf-sweeper", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop sweeping."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)

    def sweep(self) -> int:
        """Evict the robots idle now; returns how many went."""
        gone = 0
        now = self._clock()
        for placed, idle_ns in ((True, self._idle_ns), (False, self.unplaced_ns)):
            for robot in self._idle_since(now - idle_ns, placed):
                try:
                    gone += self._evict(robot, eviction_message(idle_ns / 1e9, placed))
                except Exception:
                    log.exception("evicting %s failed", robot)
        self.evicted += gone
        return gone

    def make_room(self) -> bool:
        """Evict one robot never placed, the first seen, for a robot being placed while
        ``max_robots`` are held (a sustained flood of made-up ids must not keep a real robot
        out); whether one went."""
        for robot in self._idle_since(self._clock() + 1, False):
            try:
                if self._evict(robot, MADE_ROOM):
                    self.evicted += 1
                    return True
            except Exception:
                log.exception("evicting %s failed", robot)
        return False

    def _run(self) -> None:
        while not self._stop.wait(SWEEP_INTERVAL_S):
            self.sweep()
            try:
                self.also()
            except Exception:
                log.exception("after a sweep")
