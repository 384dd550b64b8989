"""Every put or DELETE under the prefix that no part of the service takes gets an Event.

The input subscribers take ``{prefix}/robots/*/*`` and ``{prefix}/maps/*``; a client that
writes ``{prefix}/robots/r1/scan/x``, deletes a robot's key or puts on a key nothing reads would
otherwise hear nothing. :class:`KeyWatch` subscribes to ``{prefix}/**``, classifies each key
(:meth:`service.keys.Keys.odd`; the common, valid keys cost a prefix test and a split) and
reports each class (``extra_levels``, ``unknown_leaf``, ``delete``, ``map_deleted``,
``unknown_key``) at most once per interval, counting the rest in the next Event's message, so a
flood of odd keys costs a few microseconds a message and one Event a second.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

from service.keys import Keys
from service.live.stats import Stats

Report = Callable[[str, str, str, str, int], None]
"""Called with level, code, key, message and the receive time of the sample."""


class KeyWatch:
    """Reports odd keys, rate-limited per class.

    Args:
        keys: the key layout.
        report: publishes an Event about ``key``.
        clock: receive time, ns.
        interval_ns: least time between two Events of one class.
        owns_key: whether this instance reports for a key (one instance of a cluster does).
        stats: counts every odd sample this instance reports for as received and rejected.
    """

    def __init__(
        self,
        keys: Keys,
        report: Report,
        clock: Callable[[], int],
        interval_ns: int,
        owns_key: Callable[[str], bool],
        stats: Stats,
    ) -> None:
        self.keys = keys
        self.report = report
        self.clock = clock
        self.interval_ns = interval_ns
        self.owns_key = owns_key
        self.stats = stats
        self._lock = threading.Lock()
        self._last: dict[str, int] = {}
        self._held: dict[str, int] = {}

    @property
    def key_expr(self) -> str:
        """What to subscribe to."""
        return f"{self.keys.prefix}/**"

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Subscriber callback on ``{prefix}/**``."""
        self.take(str(sample.key_expr), sample.kind == zenoh.SampleKind.DELETE)

    def take(self, key: str, delete: bool) -> None:
        """Classify one put or DELETE and report it if odd (and not held back)."""
        odd = self.keys.odd(key, delete)
        if odd is None or not self.owns_key(key):
            return
        self.stats.add("received")
        self.stats.add("rejected")
        now = self.clock()
        with self._lock:
            last = self._last.get(odd.kind)
            if last is not None and now - last < self.interval_ns:
                self._held[odd.kind] = self._held.get(odd.kind, 0) + 1
                return
            self._last[odd.kind] = now
            held = self._held.pop(odd.kind, 0)
        more = f" ({held} more like it since the last such Event)" if held else ""
        self.report(odd.level, odd.code, key, odd.message + more, now)
