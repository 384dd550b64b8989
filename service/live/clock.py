"""The service's receive clock."""

from __future__ import annotations

import threading
import time


class ReceiveClock:
    """Strictly increasing receive times (ns since the epoch), so log order is total."""

    def __init__(self) -> None:
        self._last = 0
        self._lock = threading.Lock()

    def __call__(self) -> int:
        with self._lock:
            now = max(time.time_ns(), self._last + 1)
            self._last = now
            return now
