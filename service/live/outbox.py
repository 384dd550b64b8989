"""Events and other small puts, sent from a thread of their own.

A Zenoh callback must never wait for Zenoh: a put from a callback thread can block when the
subscriber it delivers to has a full queue, and if that subscriber is the one whose callback
is putting, nothing ever drains it (a burst of ~300 malformed payloads on one robot's key
deadlocked the service that way: each rejection put an Event on ``{prefix}/robots/{r}/events``,
which the same subscriber received). So every Event goes through an :class:`Outbox`: a bounded
queue (a put never blocks the caller; past the bound the message is dropped and counted) and
one thread that puts with congestion control ``DROP`` and only to other sessions, so that
even that thread never waits on this service's own subscribers. What is recorded to the log
does not depend on the outbox: Events are recorded by the caller, so a dropped publication
never changes what an audit sees.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Protocol

import zenoh

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
#: Messages the outbox holds before it drops (a few MB of Events at most).
QUEUE_MAX = 4096


class Putter(Protocol):
    """What the outbox needs of a Zenoh session."""

    def put(self, key_expr: str, payload: bytes, **kwargs: object) -> None: ...


class Outbox:
    """Puts messages on a thread of its own, never blocking the caller.

    Args:
        name: the thread's name.
        maxsize: messages held before new ones are dropped (and counted in :attr:`dropped`).
    """

    def __init__(self, name: str = "rlutf-outbox", maxsize: int = QUEUE_MAX) -> None:
        self._queue: queue.Queue[tuple[str, bytes, zenoh.Encoding] | None] = queue.Queue(maxsize)
        self._name = name
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None
        self.dropped = 0
        self.sent = 0

    def start(self, session: zenoh.Session) -> None:
        """Start putting on ``session``."""
        self._session = session
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def put(self, key: str, payload: bytes, encoding: zenoh.Encoding = JSON) -> bool:
        """Queue one message (JSON unless ``encoding`` says otherwise).

        Returns:
            ``False`` when it was dropped (the queue is full or the outbox is not running).
        """
        if self._thread is None:
            self.dropped += 1
            return False
        try:
            self._queue.put_nowait((key, payload, encoding))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    @property
    def queued(self) -> int:
        """Messages waiting."""
        return self._queue.qsize()

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued (up to ``timeout``), then stop the thread."""
        if self._thread is None:
            return
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            log.warning("outbox %s: %d messages not sent at close", self._name, self.queued)
        self._thread.join(timeout)
        self._thread = None

    def _run(self) -> None:
        session = self._session
        assert session is not None
        while True:
            item = self._queue.get()
            if item is None:
                return
            key, payload, encoding = item
            try:
                session.put(
                    key,
                    payload,
                    encoding=encoding,
                    congestion_control=zenoh.CongestionControl.DROP,
                    allowed_destination=zenoh.Locality.REMOTE,
                )
                self.sent += 1
            except zenoh.ZError:
                self.dropped += 1
                log.warning("could not publish on %s", key, exc_info=True)
