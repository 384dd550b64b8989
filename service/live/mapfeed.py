"""Maps for a running service: followed on the bus, fetched on demand, on a thread of their own.

Map puts seen by the service's subscriber and maps a robot needs (fetched with a Zenoh get from
whatever storage answers) are parsed on one thread, recorded, and broadcast to the dispatcher's
shards, so the Zenoh callbacks stay fast.

A map of real size takes a second or more to check, and a client may put maps faster than that
(a tool in a loop, a hostile peer): the puts that wait are bounded (:data:`MAX_WAITING` puts,
:data:`WAITING_BYTES` bytes). A put beyond them is not loaded, with an Event ``map_dropped`` (at
most one a second, counting the puts since the last); once the puts that waited are done, the
service fetches the stored version of every map it dropped a put of, so that it ends on what the
store holds, as if it had seen every put. A service without a store of its own (the other
processes of ``rlutf serve --processes N``, an instance with ``--no-store``) also asks the store
every :data:`LOOK_S` seconds for the versions of the maps it holds, and fetches those it is
behind on: a put Zenoh did not deliver to it (a router drops a message of many fragments that
it cannot send on within 50 ms) reaches it so.

A put is loaded once the map store holds it (:mod:`service.maps.confirmation`), so that no
service runs robots on a version the store refused or dropped. The Events said once per put
(``map_unchanged``, ``map_version_conflict``, ``invalid_map``, ``map_unconfirmed``) go out at most
once per map and code every ``event_interval_s`` (:class:`~service.live.throttle.EventThrottle`).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable

import zenoh

from schemas import SCHEMA_NAMES, EventCode, Map, StoredVersion
from service.keys import KeyError_, Keys
from service.live.dispatch import Dispatcher
from service.live.mapfetch import MapFetches
from service.live.throttle import EventThrottle
from service.logs.recording import Recorder
from service.maps.book import (
    CheckedMap,
    Held,
    LoadedMap,
    MapBook,
    MapRejected,
    VersionConflict,
    put_verdict,
)
from service.maps.confirmation import (
    StoreWatch,
    StoreWord,
    await_store,
    dropped_message,
    unconfirmed_message,
)
from service.maps.files import FileMapStore
from service.maps.store import MapStorage, room_for, stored_version, stored_versions

log = logging.getLogger(__name__)

MAP_SCHEMA = SCHEMA_NAMES[Map]

#: Map puts that may wait to be checked (the one being checked not counted).
MAX_WAITING = 4
#: Bytes of map puts that may wait to be checked; a put arriving when none waits is always
#: taken, however large (the size limit is the check's to enforce).
WAITING_BYTES = 64 * 1024 * 1024
#: Seconds between two Events ``map_dropped``.
DROP_EVENT_S = 1.0
#: Seconds between two looks at whether the store has caught up, after dropped puts.
CATCH_UP_S = 0.5
#: Maps whose dropped puts are followed by a fetch of the stored version; the puts of more
#: maps are dropped with an Event that asks for them again.
MAX_STALE = 1024
#: Seconds between two looks, by a service without a store, at the versions the store holds.
LOOK_S = 2.0

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
        event_interval_s: least time between two Events of one code about one map put
            (``event_interval_s``).
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
        event_interval_s: float = 1.0,
    ) -> None:
        self.keys = keys
        self.book = book
        self.dispatcher = dispatcher
        self.recorder = recorder
        self.clock = clock
        self.timeout_s = timeout_s
        self._global_event = global_event
        self._robot_event = robot_event
        #: The Events said once per put: one per map and code per interval.
        self.throttle = EventThrottle(event_interval_s, global_event)
        # (kind, map id, payload or robot, an offer's arrival number, the version held then, and
        # its arrival time, monotonic)
        self._tasks: queue.Queue[tuple[str, str, bytes, int, int, float] | None] = queue.Queue()
        self._woken = False  # a "wake" task is queued (an Event held back, from the store)
        self.fetches = MapFetches()  # the robots each map's fetch answers
        self._lock = threading.Lock()
        self._waiting = 0  # offers queued, not yet checked
        self._waiting_bytes = 0
        self._fetches: set[str] = set()  # maps a fetch task is queued for
        self._stale: set[str] = set()  # maps a put of which was dropped: fetched when caught up
        self._puts = 0  # map puts seen
        self._last_put: dict[str, int] = {}  # map id -> arrival number of its newest put in flight
        self._dropped = 0  # puts dropped since the last Event
        self._drop_event_at = -math.inf
        #: Whether the embedded store still has puts to store (the stored version of a map
        #: whose puts were dropped is fetched once it has none).
        self.store_busy: Callable[[], bool] = lambda: False
        #: What the map store holds of a map (the version a put must beat, and whether it has
        #: puts of it to store yet): the embedded store's own answer, or the store's on the bus.
        self.store_holds: Callable[[str], StoredVersion | None] = self._ask_store
        self._next_look: float | None = 0.0  # None: the store is this service's own
        self._watch = StoreWatch()
        self._session: zenoh.Session | None = None
        self._thread: threading.Thread | None = None

    def start(self, session: zenoh.Session) -> None:
        """Start the map thread; maps are fetched on ``session``."""
        self._session = session  # the map checker's process starts with the first map
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
        if map_id is None:
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            self._puts += 1
            taken = room_for(
                self._waiting, self._waiting_bytes, len(payload), MAX_WAITING, WAITING_BYTES
            )
            if taken:
                self._waiting += 1
                self._waiting_bytes += len(payload)
                self._last_put[map_id] = self._puts
                held = self.book.get(map_id)
                version = -1 if held is None else held.version
                self._tasks.put(("offer", map_id, payload, self._puts, version, time.monotonic()))
                return
            follow = map_id in self._stale or len(self._stale) < MAX_STALE
            if follow:
                self._stale.add(map_id)
                self._last_put[map_id] = self._puts
            self._dropped += 1
            now = time.monotonic()
            if now - self._drop_event_at < DROP_EVENT_S:
                return
            self._drop_event_at = now
            dropped, self._dropped = self._dropped, 0
            waiting, waiting_mb = self._waiting, self._waiting_bytes / 1e6
        message = dropped_message(map_id, dropped, len(payload), waiting, waiting_mb, follow)
        self._global_event("warning", EventCode.MAP_DROPPED, key, message, None)

    def embed_store(
        self,
        session: zenoh.Session,
        store: FileMapStore,
        max_bytes: int,
        report: Callable[[str, str, str, str, str], None],
    ) -> MapStorage:
        """The embedded store on ``session``, whose puts reach this feed through it.

        Map puts then come here only once the store has taken them, so that the service and its
        store cannot disagree on a put one of them dropped under a flood. ``report(kind, level,
        code, key, message)``: an Event, at most one a second per kind.
        """

        def say(code: str, level: str) -> Callable[[str, str], None]:
            return lambda key, msg: report(code, level, code, key, msg)

        storage = MapStorage(
            session,
            self.keys,
            store,
            max_bytes,
            on_error=say(EventCode.INVALID_MAP, "error"),
            checker=self.book.checker,
            on_drop=say(EventCode.MAP_DROPPED, "warning"),
            forward=self.on_sample,
            on_unwritten=say(EventCode.MAP_WRITE_FAILED, "error"),
            on_written=say(EventCode.MAP_WRITE_RESUMED, "warning"),
            on_conflict=self._store_conflict,
            on_claim=say(EventCode.STORE_IN_USE, "error"),
        )
        self.store_busy, self._next_look = storage.busy, None
        self.store_holds = storage.answer
        return storage

    def _store_conflict(self, key: str, message: str) -> None:
        """The embedded store refused a put not newer than a removed version: said per map, as
        the service's own refusals are (one every ``event_interval_s``, the last held back said
        at its end, when the map thread is woken: `rlutf map put` waits for it)."""
        map_id = self.keys.parse_map_key(key) or key
        # A subject of its own: held back with the service's own conflicts on the map (the same
        # code), the last of them replaced the store's, and the tool never saw the store's word.
        subject = f"store {map_id}"
        self.throttle.say(
            subject, "error", EventCode.MAP_VERSION_CONFLICT, key, message, self.clock()
        )
        with self._lock:
            if self._woken:  # one wake queued at most, whatever the flood of refused puts
                return
            self._woken = True
        self._tasks.put(("wake", map_id, b"", 0, -1, 0.0))

    def _ask_store(self, map_id: str) -> StoredVersion | None:
        """What the store on the bus holds of ``map_id`` (:func:`~service.maps.store.
        stored_version`), for a service without one of its own."""
        if self._session is None:
            return None
        return stored_version(self._session, self.keys, map_id, self.timeout_s)

    def need(self, map_id: str, robot: str) -> None:
        """Queue a fetch of ``map_id``, which ``robot`` waits for (one fetch queued per map)."""
        self.fetches.wait(map_id, robot)
        with self._lock:
            if map_id in self._fetches:
                return
            self._fetches.add(map_id)
        self._tasks.put(("fetch", map_id, robot.encode(), 0, -1, 0.0))

    def _run(self) -> None:
        while True:
            due = self.throttle.flush()  # the Events held back whose interval is over
            if self._stale:
                due = CATCH_UP_S if due is None else min(due, CATCH_UP_S)
            if self._next_look is not None:
                look = max(0.0, self._next_look - time.monotonic())
                due = look if due is None else min(due, look)
            try:
                task = self._tasks.get(timeout=due)
            except queue.Empty:
                self._catch_up()
                continue
            if task is None:
                return
            kind, map_id, payload, number, held_then, arrived = task
            if kind == "wake":  # an Event held back: flushed when its interval ends
                with self._lock:
                    self._woken = False
                continue
            try:
                if kind == "offer":
                    self._offer(map_id, payload, number=number, held_then=held_then, at=arrived)
                else:
                    with self._lock:
                        self._fetches.discard(map_id)
                    self._fetch(map_id)
            except Exception:
                log.exception("map task %s %s failed", kind, map_id)
            finally:
                if kind == "offer":
                    with self._lock:
                        self._waiting -= 1
                        self._waiting_bytes -= len(payload)
                        if self._last_put.get(map_id) == number:
                            del self._last_put[map_id]
            del task, payload  # a map's payload is not kept while the thread waits
            self._catch_up()

    def _catch_up(self) -> None:
        """When no put waits here or in the embedded store: load the stored version of the maps
        whose puts were dropped, and those the store holds a newer version of (:meth:`_look`)."""
        self._look()
        with self._lock:
            if self._waiting or not self._stale or self.store_busy():
                return
            stale, self._stale = sorted(self._stale), set()
            for map_id in stale:
                self._last_put.pop(map_id, None)
        for map_id in stale:
            try:
                self._refresh(map_id)
            except Exception:
                log.exception("fetching map %s after dropped puts failed", map_id)

    def _look(self) -> None:
        """Without a store of its own, every :data:`LOOK_S`: the maps the store holds newer
        versions of, with no put of them on its way here, are fetched (:class:`StoreWatch`)."""
        if self._next_look is None or time.monotonic() < self._next_look or not self._session:
            return
        self._next_look = time.monotonic() + LOOK_S
        held = {m: h for m in self.book.ids() if (h := self._held(m)) is not None}
        stored = stored_versions(self._session, self.keys, min(self.timeout_s, LOOK_S))
        behind = self._watch.behind(held, stored)
        with self._lock:
            self._stale.update(m for m in behind if m not in self._last_put)

    def _refresh(self, map_id: str) -> None:
        """Load what the store holds of ``map_id``, once it has no put of it left to store."""
        if self._session is None:
            return
        answer = self.store_holds(map_id)
        if answer is not None:
            if answer.pending:  # looked at again once they are stored
                with self._lock:
                    self._stale.add(map_id)
                return
            if answer.removed or answer.held in (None, self._held(map_id)):
                return  # nothing to fetch, or what is held here already
        for reply in self._session.get(self.keys.map(map_id), timeout=self.timeout_s):
            if reply.ok is not None:
                self._offer(map_id, reply.ok.payload.to_bytes(), quiet=True)

    def _offer(
        self,
        map_id: str,
        payload: bytes,
        quiet: bool = False,
        number: int = 0,
        held_then: int = -1,
        at: float = 0.0,
    ) -> bool:
        """Check a map, load it if it is newer; ``quiet``: a stored version fetched again, which
        is no client's put (an older one than held is no conflict to report).

        ``number``: a put's arrival number (0: a map fetched from the storage); ``held_then``:
        the version this service held when it arrived (-1: none); ``at``: when it arrived
        (monotonic). A put is loaded once the store holds it (:meth:`_store_word`). A put newer
        than ``held_then``, which conflicts now only because a newer put of the map came after
        it (and the store, say, stored that one first), was superseded, not refused: no conflict
        is reported for it."""
        key = self.keys.map(map_id)
        # Validated first, with no lock held: a big map takes a while, and the robots' inputs
        # go through the dispatcher's lock.
        try:
            checked = self.book.check(map_id, payload)
        except MapRejected as err:
            if quiet:
                log.warning("the stored map %s is not valid: %s", map_id, err)
                return False
            self.throttle.say(map_id, "error", EventCode.INVALID_MAP, key, str(err), self.clock())
            return False
        # The store's word on a put new here, asked with no lock held (a get on the bus waits);
        # the map thread alone commits, so what it said holds when the put is committed.
        store = None
        if number and put_verdict(self._held(map_id), checked.version, checked.digest) == "new":
            word = self._store_word(map_id, checked, at)
            if word.word in ("dropped", "unconfirmed"):
                self._not_loaded(map_id, checked, word)
                return False
            store = None if word.answer is None else word.answer.held
        # Order matters for replay: the map is recorded and reaches the shards at one instant
        # of the receive clock, before any input received after it.
        conflict: VersionConflict | None = None
        with self.dispatcher.lock:
            received = self.clock()
            try:
                loaded = self.book.commit(map_id, payload, checked, received, store)
            except VersionConflict as err:
                loaded, conflict = None, err
            if loaded is not None:
                self._record(loaded)
                self.dispatcher.broadcast_map(loaded)
        self.dispatcher.flush()
        with self._lock:
            later = bool(number) and self._last_put.get(map_id, number) > number
        superseded = later and checked.version > held_then
        if conflict is not None and (quiet or superseded):
            log.info("%s: %s", "superseded" if superseded else "not newer", conflict)
            return True
        if conflict is not None:
            self.throttle.say(
                map_id, "error", EventCode.MAP_VERSION_CONFLICT, key, str(conflict), received
            )
            return True  # a version is held
        if loaded is None:  # an echo of the version held
            if number:  # a client's put, whose tool waits for each service's word on it
                self.throttle.say(
                    map_id,
                    "info",
                    EventCode.MAP_UNCHANGED,
                    key,
                    f"map {map_id} version {checked.version} put: already held with this "
                    "content, nothing changed",
                    received,
                )
            return True
        self._global_event(
            "info",
            EventCode.MAP_UPDATED,
            key,
            f"map {map_id} version {loaded.version} loaded",
            received,
        )
        return True

    def _held(self, map_id: str) -> Held | None:
        """The version of ``map_id`` loaded here and its digest, if any."""
        mine = self.book.get(map_id)
        return None if mine is None else (mine.version, mine.digest)

    def _store_word(self, map_id: str, checked: CheckedMap, at: float) -> StoreWord:
        """What the store made of a put of ``map_id`` that arrived at ``at`` (it is still taking
        it while its answers say it has puts of the map to store)."""

        def pause(seconds: float) -> None:
            self.throttle.flush()  # a tool waits for the Events held back
            time.sleep(seconds)

        return await_store(
            lambda: self.store_holds(map_id), checked.version, checked.digest, at, pause=pause
        )

    def _not_loaded(self, map_id: str, checked: CheckedMap, word: StoreWord) -> None:
        """A put the store did not take (dropped under a flood; it said so), or did not say it
        took within :data:`~service.maps.confirmation.CONFIRM_S`: not loaded; what the store
        holds is loaded once it has no put of the map left to store."""
        answer = word.answer
        assert answer is not None
        with self._lock:
            if map_id in self._stale or len(self._stale) < MAX_STALE:
                self._stale.add(map_id)
        if word.word == "dropped":
            log.info("map %s version %d put not loaded: the store dropped it (holds %s)",
                     map_id, checked.version, answer.version)  # fmt: skip
            return
        message = unconfirmed_message(map_id, checked.version, answer)
        key = self.keys.map(map_id)
        self.throttle.say(map_id, "warning", EventCode.MAP_UNCONFIRMED, key, message, self.clock())

    def _record(self, loaded: LoadedMap) -> None:
        self.recorder.record(
            self.keys.map(loaded.map_id),
            MAP_SCHEMA,
            loaded.payload,
            loaded.received_ns,
            loaded.received_ns,
        )

    def _fetch(self, map_id: str) -> None:
        session, key = self._session, self.keys.map(map_id)
        if self.book.get(map_id) is not None or session is None:
            self.fetches.drop(map_id)
            return

        def get() -> bool:
            found = False
            for reply in session.get(key, timeout=self.timeout_s):
                if reply.ok is not None:
                    found = self._offer(map_id, reply.ok.payload.to_bytes()) or found
            return found

        def not_found(robots: Iterable[str]) -> None:
            for robot in robots:
                why = f"no storage answered for map {map_id!r}"
                self._robot_event(robot, "error", EventCode.MAP_NOT_FOUND, key, why)

        self.fetches.fetch(map_id, get, not_found)
