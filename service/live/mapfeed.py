"""Maps for a running service: followed on the bus, fetched on demand, on a thread of their own.

Map puts seen by the service's subscriber and maps a robot needs (fetched with a Zenoh get from
whatever storage answers) are parsed on one thread, recorded, and broadcast to the dispatcher's
shards, so the Zenoh callbacks stay fast.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import zenoh

from schemas import SCHEMA_NAMES, EventCode, Map
from service.keys import KeyError_, Keys
from service.live.dispatch import Dispatcher
from service.logs.recording import Recorder
from service.maps.book import LoadedMap, MapBook, MapRejected, VersionConflict

log = logging.getLogger(__name__)

MAP_SCHEMA = SCHEMA_NAMES[Map]

GlobalEvent = Callable[[str, str, str, str, int | None], None]
"""Publish an event not tied to a robot: level, code, key, message, time."""
RobotEvent = Callable[[str, str, str, str, str], None]
"""Publish an event about a robot: robot, level, code, key, message."""


class MapFeed:
    """Loads maps into a :class:`MapBook` and the dispatcher's shards.

    Args:
        keys: key layout.
        book: the maps held.
        dispatcher: where loaded maps are broadcast.
        recorder: where loaded maps are recorded.
        clock: the service's receive clock, ns.
        timeout_s: timeout of a map get.
        global_event: reports a bad map or key.
        robot_event: reports a map no storage has.
    """

    def __init__(
        self,
        keys: Keys,
        book: MapBook,
        dispatcher: Dispatcher,
        recorder: Recorder,
        clock: Callable[[], int],
        timeout_s: float,
        global_event: GlobalEvent,
        robot_event: RobotEvent,
    ) -> None:
        self.keys = keys
        self.book = book
        self.dispatcher = dispatcher
        self.recorder = recorder
        self.clock = clock
        self.timeout_s = timeout_s
        self._global_event = global_event
        self._robot_event = robot_event
        self._tasks: queue.Queue[tuple[str, str, bytes] | None] = queue.Queue()
        self._fetching: dict[str, float] = {}
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None

    def start(self, session: zenoh.Session) -> None:
        """Start the map thread; maps are fetched on ``session``."""
        self._session = session
        self.book.checker.start()
        self._thread = threading.Thread(target=self._run, name="rlutf-maps", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the map thread after the queued tasks."""
        self._tasks.put(None)
        if self._thread is not None:
            self._thread.join(timeout)
        self.book.checker.close()

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Subscriber callback on ``{prefix}/maps/*``: queue the map for parsing."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        try:
            map_id = self.keys.parse_map_key(key)
        except KeyError_ as err:
            self._global_event("error", EventCode.INVALID_KEY, key, str(err), None)
            return
        if map_id is not None:
            self._tasks.put(("offer", map_id, sample.payload.to_bytes()))

    def need(self, map_id: str, robot: str) -> None:
        """Queue a fetch of ``map_id``, which ``robot`` waits for."""
        self._tasks.put(("fetch", map_id, robot.encode()))

    def _run(self) -> None:
        while True:
            task = self._tasks.get()
            if task is None:
                return
            kind, map_id, payload = task
            try:
                if kind == "offer":
                    self._offer(map_id, payload)
                else:
                    self._fetch(map_id, payload.decode())
            except Exception:
                log.exception("map task %s %s failed", kind, map_id)

    def _offer(self, map_id: str, payload: bytes) -> bool:
        key = self.keys.map(map_id)
        # Validated first, with no lock held: a big map takes a while, and the robots' inputs
        # go through the dispatcher's lock.
        try:
            checked = self.book.check(map_id, payload)
        except MapRejected as err:
            self._global_event("error", EventCode.INVALID_MAP, key, str(err), self.clock())
            return False
        # Order matters for replay: the map is recorded and reaches the shards at one instant
        # of the receive clock, before any input received after it.
        conflict: VersionConflict | None = None
        with self.dispatcher.lock:
            received = self.clock()
            try:
                loaded = self.book.commit(map_id, payload, checked, received)
            except VersionConflict as err:
                loaded, conflict = None, err
            if loaded is not None:
                self._record(loaded)
                self.dispatcher.broadcast_map(loaded)
        self.dispatcher.flush()
        if conflict is not None:
            self._global_event(
                "error", EventCode.MAP_VERSION_CONFLICT, key, str(conflict), received
            )
            return True  # a version is held
        if loaded is None:
            return True
        self._global_event(
            "info",
            EventCode.MAP_UPDATED,
            key,
            f"map {map_id} version {loaded.version} loaded",
            received,
        )
        return True

    def _record(self, loaded: LoadedMap) -> None:
        self.recorder.record(
            self.keys.map(loaded.map_id),
            MAP_SCHEMA,
            loaded.payload,
            loaded.received_ns,
            loaded.received_ns,
        )

    def _fetch(self, map_id: str, robot: str) -> None:
        now = time.monotonic()
        if self.book.get(map_id) is not None or self._session is None:
            return
        if now - self._fetching.get(map_id, -1e9) < 1.0:
            return
        self._fetching[map_id] = now
        key = self.keys.map(map_id)
        found = False
        for reply in self._session.get(key, timeout=self.timeout_s):
            if reply.ok is None:
                continue
            found = self._offer(map_id, reply.ok.payload.to_bytes()) or found
        if not found:
            self._robot_event(
                robot,
                "error",
                EventCode.MAP_NOT_FOUND,
                key,
                f"no storage answered for map {map_id!r}",
            )
