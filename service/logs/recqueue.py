"""The MCAP recorder's queue: a bounded FIFO between the service's threads and the writer.

:class:`service.logs.mcaplog.McapRecorder` puts messages on it from any thread (a put never
blocks; a full queue refuses the message, which the recorder counts) and its writer thread takes
them a batch at a time.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any, NamedTuple, cast

#: A message of this many bytes or more is large (a scan of 360 beams is about 3 kB): the large
#: messages waiting hold at most :data:`LARGE_QUEUED` bytes, since the queue's length alone would
#: let 20,000 scans of 1 MB (the message limit) wait.
LARGE = 16 * 1024
#: Bytes of large messages that may wait (a map of the 64 MiB limit always fits when none waits).
LARGE_QUEUED = 256 * 1024 * 1024


Message = tuple[str, str, bytes, int, int]
"""A queued message: topic, schema name, payload, log time, publish time (a :class:`Record`'s
fields; a plain tuple is cheaper to make on the callers' threads)."""


class ConfigItem(NamedTuple):
    config: dict[str, Any]


class Stop(NamedTuple):
    pass


Item = Message | ConfigItem | Stop


class Queue:
    """A bounded FIFO with one consumer, cheaper than :class:`queue.Queue` for many producers.

    A put is an append under the GIL. ``queue.Queue`` takes its lock on every put and get, and
    producers on the Zenoh callback threads then waited for the writer thread: measured at about
    half the cost of recording a scan. Messages do not wake the consumer either: it takes what
    has come every ``poll_s`` (and at once when the queue is a quarter full or a control item
    comes), so it runs once per batch instead of once per message, which costs the service two
    thread switches per message otherwise.
    """

    def __init__(self, maxsize: int, poll_s: float) -> None:
        self._items: deque[Item] = deque()
        self._maxsize = maxsize
        self._large = 0  # bytes of large messages queued
        self._large_lock = threading.Lock()
        self._soon = max(maxsize // 4, 1)
        self._poll_s = poll_s
        self._wake = threading.Event()

    def put_nowait(self, item: Item) -> bool:
        """Append unless full (in messages, or in bytes of large messages); ``False`` when
        full."""
        items = self._items
        if len(items) >= self._maxsize:
            return False
        size = len(cast(Message, item)[2]) if type(item) is tuple else 0
        if size >= LARGE:
            with self._large_lock:
                if self._large and self._large + size > LARGE_QUEUED:
                    return False
                self._large += size
        items.append(item)
        if len(items) >= self._soon and not self._wake.is_set():
            self._wake.set()
        return True

    def put(self, item: Item) -> None:
        """Append, full or not, and wake the consumer (control items)."""
        self._items.append(item)
        self._wake.set()

    def take(self, timeout: float) -> list[Item]:
        """Every queued item, oldest first, waiting at most ``min(timeout, poll_s)`` for one
        when none is queued (then possibly none)."""
        items = self._items
        if not items:
            self._wake.clear()
            if not items:  # a put between the test and the clear has set nothing: look again
                self._wake.wait(min(timeout, self._poll_s))
        popleft = items.popleft
        taken = [popleft() for _ in range(len(items))]
        if self._large:
            sizes = (len(cast(Message, m)[2]) for m in taken if type(m) is tuple)
            large = sum(n for n in sizes if n >= LARGE)
            if large:
                with self._large_lock:
                    self._large -= large
        return taken

    def empty(self) -> bool:
        """Nothing is queued."""
        return not self._items

    def __len__(self) -> int:
        return len(self._items)
