"""Giving freed heap memory back to the system, in a process that runs for months.

Messages of a few kB (scans, their MCAP records) are allocated by glibc's malloc, not by
Python's small-object allocator. After a burst (a load spike fills the recorder queue and the
mailboxes for a few seconds) they are freed, but the pages in the middle of the heap stay with
the process: resident memory keeps the burst's high-water mark, and a 30-minute soak showed it
as steps (BENCHMARKS.md, "Soak"). ``malloc_trim(0)`` hands every free page back. It walks the
heap, so it runs every ``interval_s``, not per message.
"""

from __future__ import annotations

import time

from service.maps.helper import malloc_trim


class HeapTrimmer:
    """Calls :meth:`maybe` often; gives free heap pages back at most every ``interval_s``."""

    def __init__(self, interval_s: float = 30.0) -> None:
        self.interval_s = interval_s
        self._trim = malloc_trim()
        self._next = time.monotonic() + interval_s
        self.trims = 0

    @property
    def available(self) -> bool:
        """Whether this C library can trim its heap."""
        return self._trim is not None

    def maybe(self) -> None:
        """Trim now if ``interval_s`` has passed since the last trim."""
        now = time.monotonic()
        if now < self._next or self._trim is None:
            return
        self._next = now + self.interval_s
        self._trim()
        self.trims += 1
