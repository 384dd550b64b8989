"""At most one Event per subject and interval, the ones held back said at its end.

An Event per map put (``map_unchanged``, ``map_version_conflict``) makes a flood of puts a
flood of Events from every service process. :class:`EventThrottle` lets one Event per subject
(a map and a code) out per interval, as the service does for a robot's ``invalid_message``
(:meth:`service.live.admission.Gate.rejection`), but does not wait for a next one to say those
held back: the last one held back goes out when the interval ends, counting the others. A tool
that waits for the service's word on its own put (``rlutf map put``) so gets it within the
interval, even when its put came right after another one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import NamedTuple

#: Subjects the throttle remembers; subjects (map ids) can be invented without end, so past
#: this the ones with nothing held back are forgotten (at worst one more Event for each), and
#: while those held back fill it, a new subject's Event goes out unthrottled (each costs a put,
#: and its check, first).
SUBJECTS_KEPT = 8192

Send = Callable[[str, str, str, str, int | None], None]
"""Send an Event: level, code, key, message, stamp (ns; ``None``: now)."""


class _Held(NamedTuple):
    """The last Event held back for a subject, and how many were held back with it."""

    level: str
    code: str
    key: str
    message: str
    stamp: int | None
    times: int


def more_like_it(message: str, others: int) -> str:
    """``message``, counting the ``others`` held back since the last Event of its kind."""
    return f"{message} ({others} more like it since the last such Event)" if others else message


class EventThrottle:
    """At most one Event per subject every ``interval_s``; the last one held back is sent at the
    end of the interval, with the number of the others held back with it.

    Thread-safe. Nothing is sent by itself: :meth:`flush` sends the Events due, and says when the
    next one will be (its caller's thread calls it then).

    Args:
        interval_s: least time between two Events of a subject (``event_interval_s``); 0: no
            Event is held back.
        send: sends an Event.
        clock: monotonic seconds.
    """

    def __init__(
        self, interval_s: float, send: Send, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.interval_s = interval_s
        self._send = send
        self._clock = clock
        self._lock = threading.Lock()
        self._last: dict[tuple[str, str], float] = {}  # subject -> when its last Event went out
        self._held: dict[tuple[str, str], _Held] = {}
        self.held_back = 0  # Events held back so far (tests, figures)

    def say(
        self,
        subject: str,
        level: str,
        code: str,
        key: str,
        message: str,
        stamp: int | None = None,
    ) -> None:
        """Send an Event about ``subject`` (with its ``code``, the throttle's subject) now, or
        hold it back until the end of the interval if one went out less than it ago."""
        now = self._clock()
        about = (subject, code)
        with self._lock:
            last = self._last.get(about)
            if last is not None and now - last < self.interval_s:
                before = self._held.get(about)
                times = 1 if before is None else before.times + 1
                self._held[about] = _Held(level, code, key, message, stamp, times)
                self.held_back += 1
                return
            if last is None and len(self._last) >= SUBJECTS_KEPT:
                self._forget()
            if len(self._last) < SUBJECTS_KEPT:  # else said, not remembered
                self._last[about] = now
        self._send(level, code, key, message, stamp)

    def _forget(self) -> None:
        """Forget the subjects with nothing held back (``_lock`` held)."""
        for about in list(self._last):
            if about not in self._held:
                del self._last[about]

    def flush(self) -> float | None:
        """Send the Events held back whose interval is over; seconds until the next is due
        (``None``: none is held back)."""
        now = self._clock()
        due: list[_Held] = []
        soonest: float | None = None
        with self._lock:
            for about, held in list(self._held.items()):
                left = self._last[about] + self.interval_s - now
                if left > 0:
                    soonest = left if soonest is None else min(soonest, left)
                    continue
                del self._held[about]
                self._last[about] = now
                due.append(held)
        for held in due:
            message = more_like_it(held.message, held.times - 1)
            self._send(held.level, held.code, held.key, message, held.stamp)
        return soonest
