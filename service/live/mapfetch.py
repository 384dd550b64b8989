"""Fetches of a map that robots' requests wait for, and their answers.

An InitialPose or a Relocalize naming a map the service does not hold makes it fetch the map
from whatever storage answers; when none does, every robot that asked gets ``map_not_found``
(WIRE.md, Relocalize). Several robots may name one missing map at once (a fleet put on a map
nobody stored, an operator's typo pasted into a script): one fetch serves them all, and one a
second at most goes out per map, but each robot that asked is answered. Before, the robots
whose request came while a fetch of the map was queued or had just been made got no answer.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable

#: Least time between two fetches of one map, seconds (a request within it gets the answer of
#: the fetch before).
FETCH_INTERVAL_S = 1.0
#: Robots kept waiting on one map's fetch, at most (ids are a client's to invent).
WAITERS_PER_MAP = 4096


class MapFetches:
    """The robots waiting on each map's fetch, and when each map was fetched, with what result.

    Thread-safe: :meth:`wait` is called from the service's threads, :meth:`fetch` from the map
    thread.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiting: dict[str, dict[str, None]] = {}  # map id -> robots, in order of asking
        self._last: dict[str, tuple[float, bool]] = {}  # map id -> (monotonic, found)

    def wait(self, map_id: str, robot: str) -> None:
        """Note that ``robot`` waits on ``map_id`` (before a fetch of it is queued)."""
        with self._lock:
            robots = self._waiting.setdefault(map_id, {})
            if len(robots) < WAITERS_PER_MAP:
                robots[robot] = None

    def drop(self, map_id: str) -> None:
        """Forget the robots waiting on ``map_id`` (it is loaded: their requests apply)."""
        with self._lock:
            self._waiting.pop(map_id, None)

    def fetch(
        self,
        map_id: str,
        get: Callable[[], bool],
        not_found: Callable[[Iterable[str]], None],
    ) -> None:
        """Fetch ``map_id`` with ``get`` (whether a storage answered with it), unless it was
        fetched within :data:`FETCH_INTERVAL_S`; call ``not_found`` with the robots waiting on
        it when none did. Nothing to do when no robot waits (a fetch before took them)."""
        with self._lock:
            robots = list(self._waiting.pop(map_id, {}))
            last = self._last.get(map_id)
        if not robots:
            return
        now = time.monotonic()
        if last is not None and now - last[0] < FETCH_INTERVAL_S:
            found = last[1]
        else:
            found = get()
            with self._lock:
                self._last[map_id] = (now, found)
                if len(self._last) > 4 * WAITERS_PER_MAP:  # ids of made-up maps
                    self._last = {
                        m: v for m, v in self._last.items() if now - v[0] < FETCH_INTERVAL_S
                    }
        if not found:
            not_found(robots)
