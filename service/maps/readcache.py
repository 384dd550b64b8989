"""The maps the embedded store read for gets, kept a moment for the gets that follow.

The store answers a get on ``{prefix}/maps/{map_id}`` (``rlutf/maps/**`` asks for every map)
from its files, in the Zenoh callback. Each get read the whole file and made a new payload of
it: 2,000 gets on ``rlutf/**`` against a store holding a 20 MB map cost the service 14 s of CPU,
and three robots beside it lost 70 poses. A payload read is now answered again to the gets of
the next :data:`REUSE_S` (a Zenoh payload handed on again is not copied), at most
:data:`REUSE_BYTES` of them at once; a get after a put or removal of the map reads it anew.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import zenoh

from service.maps.book import Held

#: Seconds a payload read is answered again.
REUSE_S = 1.0
#: Bytes of payloads kept at once at most (a larger map is read for each get).
REUSE_BYTES = 256 * 1024 * 1024


class ReadCache:
    """Payloads read for gets, by map id, each with the version and digest it was read at.

    Args:
        clock: monotonic seconds.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._held: dict[str, tuple[float, Held, zenoh.ZBytes, int]] = {}
        self._lock = threading.Lock()
        self.reads = 0  # payloads read (not answered again)

    def payload(
        self, map_id: str, held: Held, read: Callable[[], bytes | None]
    ) -> zenoh.ZBytes | None:
        """The payload of ``map_id`` at ``held`` (the version and digest the store holds):
        the one read less than :data:`REUSE_S` ago at the same version and digest, else
        ``read()`` (``None``: none stored; what it raises goes to the caller)."""
        now = self._clock()
        with self._lock:
            hit = self._held.get(map_id)
            if hit is not None and hit[1] == held and 0 <= now - hit[0] < REUSE_S:
                return hit[2]
        data = read()
        self.reads += 1
        if data is None:
            return None
        payload = zenoh.ZBytes(data)
        with self._lock:
            for old in [m for m, h in self._held.items() if m == map_id or now - h[0] >= REUSE_S]:
                del self._held[old]
            if sum(h[3] for h in self._held.values()) + len(data) <= REUSE_BYTES:
                self._held[map_id] = (now, held, payload, len(data))
                # dropped when its second is over, not at the next get (a single get of a
                # large map kept it in memory for as long as no other get came)
                timer = threading.Timer(REUSE_S, self._expire, (map_id, now))
                timer.daemon = True
                timer.start()
        return payload

    def _expire(self, map_id: str, read_at: float) -> None:
        with self._lock:
            hit = self._held.get(map_id)
            if hit is not None and hit[0] == read_at:
                del self._held[map_id]

    def held_bytes(self) -> int:
        """Bytes of payloads kept now."""
        with self._lock:
            return sum(h[3] for h in self._held.values())
