"""Maps from a ``nav_msgs/msg/OccupancyGrid`` topic (``ros2.map_topic``), imported one at a time.

Polygonizing a grid takes a while, so it is not done on a Zenoh thread: one thread of its own
imports the grids in turn. Grids that come during an import wait, :data:`WAITING` at most; one
more drops the oldest waiting with an Event (the map server's newest map is the one wanted), so
a flood of grids costs one import at a time and a few grids waiting, never a thread or a copy
per sample.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from collections.abc import Callable

import zenoh

from schemas import SchemaError
from service.config import Ros2Settings
from service.keys import printable
from service.ros2 import convert, names

log = logging.getLogger(__name__)

#: Grids waiting for the import thread at most.
WAITING = 2

Reject = Callable[[str | None, str, str, int], None]
"""Report bad input: robot (``None``), key, what is wrong, receive time (ns)."""


class GridImports:
    """Imports the grids of the map topic on one thread and puts each map (``put_map``)."""

    def __init__(
        self,
        settings: Ros2Settings,
        reject: Reject,
        clock: Callable[[], int],
        put_map: Callable[[str, bytes], None],
    ) -> None:
        self.settings = settings
        self.reject = reject
        self.clock = clock
        self.put_map = put_map
        self.replaced = 0  # grids dropped for newer ones before their import
        self._waiting: deque[tuple[str, names.DataKey, bytes, int]] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._thread: threading.Thread | None = None

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Subscriber callback: the grid waits for the import thread."""
        key = str(sample.key_expr)
        dk = names.parse_data_key(key, self.settings.domain_id)
        if dk is None:
            return
        item = (key, dk, sample.payload.to_bytes(), self.clock())
        dropped = None
        with self._cond:
            if self._closed:
                return
            if len(self._waiting) >= WAITING:
                self.replaced += 1
                dropped = self._waiting.popleft()
            self._waiting.append(item)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="rlutf-ros2-maps")
                self._thread.daemon = True
                self._thread.start()
            self._cond.notify()
        if dropped is not None:
            why = f"map not imported: {WAITING} newer grids came during an import; the newest go in"
            self.reject(None, dropped[0], why, dropped[3])

    def close(self) -> None:
        """Stop taking grids (an import under way ends on its own)."""
        with self._cond:
            self._closed = True
            self._waiting.clear()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._waiting and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                item = self._waiting.popleft()
            try:
                self._import(*item)
            except Exception:  # the thread must go on with the next grid
                log.exception("map import from %s failed", printable(item[0]))

    def _import(self, key: str, dk: names.DataKey, raw: bytes, received: int) -> None:
        from service.maps.mapimport import MapImportError, grid_to_map

        map_id = self.settings.robot(dk.namespace).map_id or self.settings.map_id
        try:
            if dk.msgtype != convert.OCCUPANCY_GRID:
                raise convert.CdrError(f"{dk.topic} carries {dk.msgtype}, expected a grid")
            if map_id is None:
                raise convert.CdrError("no map id for ROS maps: give ros2.map_id (--ros-map)")
            grid, stamp = convert.occupancy_grid(raw)
            # Newer grids give newer versions: the stamp in ms (the receive time without one).
            version = (stamp or received) // 1_000_000
            result = grid_to_map(grid, map_id=map_id, version=version)
        except (SchemaError, MapImportError, ValueError) as err:
            self.reject(None, key, f"map not imported: {err}", received)
            return
        log.info("map %s v%d imported from %s", map_id, version, printable(dk.topic))
        self.put_map(map_id, json.dumps(result.map).encode())
