"""A bound on the Events about robots that a service sends, over all robots, per code.

The Events a client can cause on a robot id are held back per robot (one per
``event_interval_s``: :meth:`service.live.admission.Gate.rejection`, the engine's own), but ids
are a client's to invent: 10,000 puts on 10,000 made-up ids in a quarter of a second were about
2,300 Events, each a WARNING line of the service's log, and the real fleet lost scans to the
work. :class:`EventBudget` lets the Events of at most :data:`ROBOTS_PER_WINDOW` robots per code
out per :data:`WINDOW_NS`; the others are folded into one Event per code on
``{prefix}/events`` when the window ends, "N more like it from M robots". What it bounds is the
publication and the log line: every Event is still recorded (replay needs ``robot_evicted``; an
audit reads the others), and Health counts every rejected input.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field
from typing import Final

from schemas import EventCode

#: Robots whose Events of one code go out per window, at most.
ROBOTS_PER_WINDOW: Final = 20
#: The window, ns.
WINDOW_NS: Final = 1_000_000_000
#: Robot ids the folded Events of a code are counted over, at most (past it: "more than").
FOLDED_IDS_KEPT: Final = 65_536
#: The codes an input on a robot id nobody uses can cause, so the codes a flood of ids makes.
BOUNDED: Final = frozenset(
    (
        EventCode.INVALID_MESSAGE,
        EventCode.STAMP_REJECTED,
        EventCode.NOT_INITIALIZED,
        EventCode.MAP_NOT_FOUND,
        EventCode.ROBOT_EVICTED,
        EventCode.FRAME_MISMATCH,
        EventCode.ODOMETRY_NOT_FOUND,
    )
)
#: Input leaves that are an operator's request: their Events are answers, always sent (`rlutf
#: initialpose` waits for its own).
REQUESTS: Final = ("/initialpose", "/relocalize")


@dataclass
class _Folded:
    """The Events of one code held back in a window."""

    level: str
    about: str
    message: str | bytes  # bytes: the encoded Event, read only if it is the last
    events: int = 0
    robots: set[str] = field(default_factory=set)
    more_robots: bool = False  # past FOLDED_IDS_KEPT


@dataclass(frozen=True)
class Folded:
    """What one code's Events held back in a window add up to.

    Attributes:
        level: the level of the last one held back.
        code: their code.
        about: the key the last one was about.
        message: the Event to send for them all.
    """

    level: str
    code: str
    about: str
    message: str


class EventBudget:
    """At most ``robots`` robots' Events of a code every ``window_ns``; the rest counted.

    Thread-safe (the callers are the bus's callback threads, the loop and the sweeper).

    Args:
        robots: robots per code and window whose Events go out.
        window_ns: the window, ns.
    """

    def __init__(self, robots: int = ROBOTS_PER_WINDOW, window_ns: int = WINDOW_NS) -> None:
        self.robots = robots
        self.window_ns = window_ns
        self._lock = threading.Lock()
        self._start: int | None = None
        self._sent: dict[str, set[str]] = {}  # code -> robots whose Events went out this window
        self._folded: dict[str, _Folded] = {}
        self.held_back = 0  # Events held back so far (Health, tests)

    def admit(
        self, robot: str, level: str, code: str, about: str, message: str | bytes, now: int
    ) -> bool:
        """Whether an Event about ``robot`` goes out now; if not, it is counted for the Event
        :meth:`due` makes of its code at the end of the window. ``message`` may be the encoded
        Event instead (``level`` and ``about`` are then read from it, if needed)."""
        if code not in BOUNDED or about.endswith(REQUESTS):
            return True
        with self._lock:
            if self._start is None or now - self._start >= self.window_ns:
                self._start, self._sent = now, {}
            sent = self._sent.setdefault(code, set())
            if robot in sent:
                return True
            if len(sent) < self.robots:
                sent.add(robot)
                return True
            folded = self._folded.get(code)
            if folded is None:
                folded = self._folded[code] = _Folded(level, about, message)
            folded.level, folded.about, folded.message = level, about, message
            folded.events += 1
            if len(folded.robots) < FOLDED_IDS_KEPT:
                folded.robots.add(robot)
            else:
                folded.more_robots |= robot not in folded.robots
            self.held_back += 1
            return False

    def due(self, now: int) -> list[Folded]:
        """The Events that say what was held back, once its window is over (each code's once
        a window at most)."""
        with self._lock:
            if self._start is None or now - self._start < self.window_ns or not self._folded:
                return []
            folded, self._folded = self._folded, {}
            self._start, self._sent = now, {}
        window = self.window_ns / 1e9
        out = []
        for code, f in sorted(folded.items()):
            level, about, message = f.level, f.about, f.message
            if isinstance(message, bytes):  # an Event the engine made: its own fields
                ev = json.loads(message)
                level, about, message = ev["level"], ev.get("key", ""), ev["message"]
            more = "more than " if f.more_robots else ""
            out.append(
                Folded(
                    level,
                    code,
                    about,
                    f"{f.events} more like it from {more}{len(f.robots)} robots not sent one by "
                    f"one (Events of a code about at most {self.robots} robots every {window:g} "
                    f"s; Health counts every rejected input); the last: {message}",
                )
            )
        return out
