"""Every put or DELETE under the prefix that no part of the service takes gets an Event.

The input subscribers take ``{prefix}/robots/*/*`` and ``{prefix}/maps/*``; a client that
writes ``{prefix}/robots/r1/scan/x``, deletes a robot's key or puts on a key nothing reads would
otherwise hear nothing. :class:`KeyWatch` subscribes to ``{prefix}/**``, classifies each key
(:meth:`service.keys.Keys.odd`; the common, valid keys cost a prefix test and a split) and
reports each class (``extra_levels``, ``unknown_leaf``, ``delete``, ``map_deleted``,
``unknown_key``) at most once per interval, counting the rest in the next Event's message, so a
flood of odd keys costs a few microseconds a message and one Event a second. The samples wait
in a ring channel on Zenoh's side that the KeyWatch's thread drains every :data:`DRAIN_S`: a
Python callback per sample of the whole fleet cost the busiest process a GIL acquisition per
message (0.08 ms of CPU per scan at 50 robots); the ring never holds up the link, and when a
flood overfills it between two drains, the oldest samples go uncounted (the Events still say
that such keys arrive).

The Events go out from a thread of the KeyWatch's own, through a short queue that drops (and
counts) when full: a Zenoh callback that puts can wait on the very channel whose thread runs it
(issue 19), so no callback here waits for Zenoh. :meth:`KeyWatch.limited` offers the same rate
limit and thread to other reports of bad keys (invalid robot ids, map keys the store rejects).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from service.config import Settings
from service.keys import Keys
from service.live.stats import Stats

log = logging.getLogger(__name__)

#: Events waiting for the KeyWatch's thread; more are dropped (and counted).
_QUEUE = 256
#: Samples the ring channel holds between two drains (the oldest go first when it is full).
RING = 8192
#: Seconds between two drains of the ring channel.
DRAIN_S = 0.02

Report = Callable[[str, str, str, str, int], None]
"""Called with level, code, key, message and the receive time of the sample."""


class KeyWatch:
    """Reports odd keys, rate-limited per class.

    Args:
        keys: the key layout.
        report: publishes an Event about ``key``.
        clock: receive time, ns.
        settings: ``event_interval_s`` is the least time between two Events of one class.
        owns_key: whether this instance reports for a key (one instance of a cluster does).
    """

    def __init__(
        self,
        keys: Keys,
        report: Report,
        clock: Callable[[], int],
        settings: Settings,
        owns_key: Callable[[str], bool],
    ) -> None:
        self.keys = keys
        self.report = report
        self.clock = clock
        self.interval_ns = int(settings.event_interval_s * 1e9)
        self.owns_key = owns_key
        self.stats: Stats | None = None
        self._subscriber: Any = None
        self._lock = threading.Lock()
        self._last: dict[str, int] = {}
        self._held: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, str, str, str, int] | None] = queue.Queue(_QUEUE)
        self._thread: threading.Thread | None = None
        self.dropped = 0

    def start(self, session: zenoh.Session, stats: Stats) -> None:
        """Start the thread that publishes the Events and subscribe to ``{prefix}/**``.

        Args:
            session: the service's session.
            stats: counts every odd sample this instance reports for as received and rejected.
        """
        self.stats = stats
        self._thread = threading.Thread(target=self._run, name="rlutf-keywatch", daemon=True)
        self._thread.start()
        # A ring channel, drained by the thread: no Python callback per sample (every scan
        # and odometry reading of the fleet matches), and a flood never holds up the link.
        self._subscriber = session.declare_subscriber(
            self.key_expr, zenoh.handlers.RingChannel(RING)
        )

    def close(self) -> None:
        """Unsubscribe, publish what is queued, then stop the thread."""
        if self._subscriber is not None:
            with contextlib.suppress(Exception):  # already gone with the session
                self._subscriber.undeclare()
            self._subscriber = None
        if self._thread is None:
            return
        with contextlib.suppress(queue.Full):
            self._queue.put(None, timeout=1.0)
        self._thread.join(2.0)
        self._thread = None

    def _run(self) -> None:
        while True:
            item: tuple[str, str, str, str, int] | bool | None
            try:
                item = self._queue.get(timeout=DRAIN_S)
            except queue.Empty:
                item = False
            self._drain()
            if item is None:
                return
            if item:
                assert isinstance(item, tuple)
                try:
                    self.report(*item)
                except Exception:  # a report that fails must not end the thread
                    log.exception("publishing an Event about key %r failed", item[2])

    def _drain(self) -> None:
        """Classify what the ring channel holds."""
        sub = self._subscriber
        if sub is None:
            return
        for _ in range(RING):
            try:
                sample = sub.try_recv()
            except Exception:  # undeclared meanwhile
                return
            if sample is None:
                return
            self.on_sample(sample)

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
        if self.stats is not None:
            self.stats.add("received")
            self.stats.add("rejected")
        self.limited(odd.kind, odd.level, odd.code, key, odd.message, self.clock())

    def limited(self, kind: str, level: str, code: str, key: str, message: str, at: int) -> None:
        """Report an Event of class ``kind``, unless one of that class went out less than the
        interval ago (then it is counted in the next one's message). Never blocks."""
        with self._lock:
            last = self._last.get(kind)
            if last is not None and at - last < self.interval_ns:
                self._held[kind] = self._held.get(kind, 0) + 1
                return
            self._last[kind] = at
            held = self._held.pop(kind, 0)
        more = f" ({held} more like it since the last such Event)" if held else ""
        try:
            self._queue.put_nowait((level, code, key, message + more, at))
        except queue.Full:
            self.dropped += 1
