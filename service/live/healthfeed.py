"""Map health in the live service: the workers' evidence merged, published, recorded, answered.

Every instance shares the evidence it counted and merges the others' (:mod:`service.evidence`),
and one of them, the owner of the map's MapHealth key among the live instances, puts and
records each map's MapHealth: a report of the whole fleet, from one instance.

Worker processes count each scan's map health evidence beside the localizer and hand it on
with a batch's outputs at most once a second (``evidence`` outputs,
:class:`service.live.worker.HandOver`). :class:`HealthFeed` merges it into one
:class:`service.maphealth.MapHealthEngine` per service, puts each map's MapHealth on
``{prefix}/maphealth/{map_id}`` when it changed (at most once a second), records it (schema
``rlutf.MapHealth``) and answers gets there. A map version starts its evidence afresh when the
first evidence of it arrives (the map book holds the version the robots are on).

The other instances' evidence arrives on a Zenoh callback thread, which only checks its key
and size and hands the payload to a thread of the feed's own (:meth:`HealthFeed.declare`):
decompressing, merging and building a report run there, not on the thread that delivers the
bus's samples, and so does waiting for a map version's walls at its first evidence (with worker
processes this process holds no map: the process that validates maps builds it and sends it back,
:meth:`service.maps.book.MapBook.world_of`). The workers' evidence goes there too: it comes
with their outputs, on the thread that publishes the poses, and a report walks the map's grid
and builds a polygon per change (a warehouse with 2000 pallets the map lacks: a second and
more), which held back every robot's pose that came after it.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Callable, Iterable
from typing import Protocol

import zenoh

from rlutf.map import Map as World
from schemas import SCHEMA_NAMES, EventCode, MapHealth
from service.evidence import decode_evidence, encode_evidence
from service.keys import Keys
from service.maphealth import Handed, MapHealthEngine
from service.maps.book import MapBook, MapRejected
from service.maps.store import room_for

log = logging.getLogger(__name__)

MAPHEALTH_SCHEMA = SCHEMA_NAMES[MapHealth]
#: Other instances' evidence payloads waiting to be merged at most. An instance shares at most
#: one a second, so a fleet of a few instances never fills it; a flood does, and what does not
#: fit is dropped with an Event.
WAITING = 32
#: Bytes of those payloads at most (each may be up to ``max_map_bytes``, 64 MiB by default: 32
#: of them were 2 GiB); one is always taken when none waits.
WAITING_BYTES = 128 << 20
JSON = zenoh.Encoding.APPLICATION_JSON
#: A map the validating process could not build for map health is asked for again this much
#: later, seconds (each try decodes the whole map there).
RETRY_S = 60.0

Publish = Callable[[str, bytes], None]
Record = Callable[[str, str, bytes, int, int], None]  # key, schema, payload, log time, stamp


class Limited(Protocol):
    """Reports an Event of a class at most once an interval (:class:`~.keywatch.KeyWatch`)."""

    def limited(self, kind: str, level: str, code: str, key: str, text: str, at: int) -> None: ...


class HealthFeed:
    """The service's map health.

    Args:
        keys: the key layout.
        maps: the service's loaded maps.
        publish: puts a payload on a key.
        record: records a message (key, schema, payload, receive time, stamp).
        clock: the service clock, ns.

    :meth:`share_as` makes it one of several instances: it puts the evidence counted here for
    the others and merges theirs, and reports the maps it is told to (one instance of those
    alive reports each map).
    """

    def __init__(
        self,
        keys: Keys,
        maps: MapBook,
        publish: Publish,
        record: Record,
        clock: Callable[[], int],
    ) -> None:
        self.keys = keys
        self.maps = maps
        self.publish = publish
        self.record = record
        self.clock = clock
        self.engine = MapHealthEngine(keys)
        self._lock = threading.Lock()
        self.instance: str | None = None  # None: evidence kept here (a replay, a test)
        self.max_bytes = 64 << 20
        self.reports: Callable[[str], bool] = lambda key: True
        self.events: Limited | None = None
        self._merging: Merging | None = None  # the feed's own thread, once declared
        self._failed: dict[str, tuple[int, int]] = {}  # a version not built, when to retry

    def share_as(
        self,
        instance: str,
        max_bytes: int,
        reports: Callable[[str], bool],
        events: Limited | None = None,
    ) -> None:
        """Share the evidence counted here as ``instance`` and merge the other instances'
        (:meth:`declare`, payloads up to ``max_bytes``); put and record the MapHealth of the
        keys ``reports`` says this instance reports; a payload that cannot be merged is an
        Event ``invalid_message`` from ``events`` (one a second)."""
        self.instance, self.max_bytes, self.reports = instance, max_bytes, reports
        self.events = events

    def refused(self, key: str, problem: str) -> None:
        """An Event ``invalid_message`` for evidence from ``key`` not merged (one a second)."""
        if self.events is not None:
            code = EventCode.INVALID_MESSAGE
            self.events.limited("evidence", "warning", code, key, problem, self.clock())

    def on_evidence(self, handed: Iterable[Handed]) -> None:
        """Merge evidence handed on by a worker; share it with the other instances; put and
        record what is due. Once :meth:`declare` d, merged and reported on the feed's own
        thread: the caller publishes the poses."""
        handed = list(handed)
        if self.instance is not None and handed:
            self.publish(self.keys.mapevidence(self.instance), encode_evidence(handed))
        if self._merging is not None:
            self._merging.own(handed)
        else:
            self._merge(handed)

    def declare(self, session: zenoh.Session) -> Merging:
        """Subscribe to the other instances' evidence (``{prefix}/service/*/mapevidence``) and
        merge it, and this instance's own, on a thread of the feed's own. Returns what
        undeclares both."""
        self._merging = Merging(self, session)
        return self._merging

    def check(self, sample: zenoh.Sample) -> bytes | None:
        """The payload of another instance's evidence to merge, or ``None`` (this instance's
        own, a delete, or over the size limit: refused with an Event)."""
        key = str(sample.key_expr)
        if self.instance is None or key == self.keys.mapevidence(self.instance):
            return None
        if sample.kind != zenoh.SampleKind.PUT:
            return None
        size = len(sample.payload)
        if size > self.max_bytes:
            self.refused(key, f"map evidence of {size} bytes: over max_map_bytes")
            return None
        return sample.payload.to_bytes()

    def on_shared(self, payload: bytes, report: bool = True) -> str | None:
        """Merge evidence another instance shared (``{prefix}/service/{instance}/mapevidence``);
        put and record what is due (unless not ``report``). Returns why the payload was
        refused, else ``None``."""
        try:
            handed = decode_evidence(payload, self.max_bytes)
        except ValueError as err:
            return str(err)
        return self._merge(handed, report)

    def _merge(self, handed: list[Handed], report: bool = True) -> str | None:
        worlds = self._worlds(handed)  # before the lock: it may wait for the validating process
        try:
            with self._lock:
                for map_id, version, world in worlds:
                    self.engine.register_map(map_id, version, world)
                self.engine.merge(handed)
        except ValueError as err:  # a grid of another shape than this map's
            return str(err)
        if report:
            self.report_due()
        return None

    def report_due(self) -> None:
        """Put and record the MapHealth of every map that is due."""
        with self._lock:
            now = self.clock()
            due = self.engine.due(now, self.reports)
        for out in due:
            self.publish(out.key, out.payload)
            self.record(out.key, MAPHEALTH_SCHEMA, out.payload, now, out.stamp_ns)

    def _worlds(self, handed: list[Handed]) -> list[tuple[str, int, World]]:
        """The maps of the versions evidence comes for that are not registered yet (their
        walls place the changes). With worker processes this process holds no map: the
        validating process builds it and sends it back, at the version's first evidence only
        (decoding and validating a 10 MB map here held the interpreter's lock for up to 0.8 s
        at a time, from every thread of the process). A map that cannot be had is asked for
        again :data:`RETRY_S` later; its evidence is dropped meanwhile."""
        out: list[tuple[str, int, World]] = []
        for map_id, version in dict.fromkeys((h.map_id, h.version) for h in handed):
            loaded = self.maps.get(map_id)
            if loaded is None or loaded.version != version:
                continue
            with self._lock:
                known = self.engine.version(map_id)
            failed = self._failed.get(map_id)
            if known == version or (
                failed is not None and failed[0] == version and self.clock() < failed[1]
            ):
                continue
            try:
                world = self.maps.world_of(loaded)
            except MapRejected as err:
                log.warning("map health of %r version %d: %s", map_id, version, err)
                self._failed[map_id] = (version, self.clock() + int(RETRY_S * 1e9))
                continue
            self._failed.pop(map_id, None)
            out.append((map_id, version, world))
        return out

    def on_query(self, query: zenoh.Query) -> None:
        """Answer gets on ``{prefix}/maphealth/*`` with the current MapHealth of each map asked
        (only those: a report may walk a large map's grid, and a get of one map made one for
        every map)."""
        with query:
            ke = query.key_expr
            with self._lock:
                now = self.clock()
                keys = [(m, self.keys.maphealth(m)) for m in self.engine.map_ids()]
                asked = [(k, m) for m, k in keys if ke.intersects(zenoh.KeyExpr(k))]
                answers = [(k, self.engine.answer(m, now)) for k, m in asked]
            for key, payload in answers:
                if payload is not None:
                    query.reply(key, payload, encoding=JSON)


#: The token that wakes the merging thread for this instance's own evidence (kept aside).
_OWN: tuple[str, bytes] = ("", b"")


class Merging:
    """The evidence merged and reported on a thread of our own: the other instances' (checked
    on Zenoh's callback thread) and this instance's workers' (:meth:`own`).

    The callback takes the payload out of the sample (the bus's buffer is not kept) and queues
    it, up to :data:`WAITING` payloads; one that does not fit is dropped with an Event (its
    counts are lost to this instance's reports, and the Event says so). This instance's own
    evidence is never dropped and never waits: it is kept aside (the thread that hands it on
    publishes the poses, and a flood of other instances' payloads must not hold it up) and
    merged first, before each payload of another instance, so what is kept aside is at most what
    one payload's merge and one report let in.
    """

    def __init__(self, feed: HealthFeed, session: zenoh.Session) -> None:
        self._feed = feed
        self._waiting: queue.Queue[tuple[str, bytes] | None] = queue.Queue(WAITING)
        self._own: list[list[Handed]] = []
        self._own_lock = threading.Lock()
        self._bytes = 0  # of the other instances' payloads waiting
        self._bytes_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="rlutf-evidence", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(feed.keys.mapevidence("*"), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = self._feed.check(sample)
        if payload is None:
            return
        key = str(sample.key_expr)
        with self._bytes_lock:
            waiting, held = self._waiting.qsize(), self._bytes
            taken = room_for(waiting, held, len(payload), WAITING, WAITING_BYTES)
            if taken:
                try:
                    self._waiting.put_nowait((key, payload))
                    self._bytes += len(payload)
                except queue.Full:  # own evidence's wake-up took the last place meanwhile
                    taken = False
        if not taken:
            self._feed.refused(
                key,
                f"map evidence dropped: {waiting} payloads ({held / 1e6:.1f} MB) already wait to "
                "be merged",
            )

    def own(self, handed: list[Handed]) -> None:
        """Merge and report this instance's evidence on the thread (never waits)."""
        with self._own_lock:
            self._own.append(handed)
            first = len(self._own) == 1
        if first:  # wake the thread; a full queue wakes it anyway, and own is taken first
            with contextlib.suppress(queue.Full):
                self._waiting.put_nowait(_OWN)

    def _run(self) -> None:
        # One item at a time: the queue stays the only buffer (a batch taken out of it would
        # let as many more in). A report is built only when one is due (once a second a map),
        # so asking after every item costs nothing more.
        while (item := self._waiting.get()) is not None:
            self._take_own()
            if item is not _OWN:
                self._take(item)
            self._take_own()
            try:
                self._feed.report_due()
            except Exception:  # a bug here must not end the merging
                log.exception("map health report")
        self._take_own()

    def _take_own(self) -> None:
        with self._own_lock:
            aside, self._own = self._own, []
        for handed in aside:
            try:
                self._feed._merge(handed, report=False)  # as on_evidence did
            except Exception:  # a bug here must not end the merging
                log.exception("map evidence")

    def _take(self, item: tuple[str, bytes]) -> None:
        key, payload = item
        with self._bytes_lock:
            self._bytes -= len(payload)
        try:
            problem = self._feed.on_shared(payload, report=False)
        except Exception:  # a bug here must not end the merging
            log.exception("map evidence")
            return
        if problem is not None:
            self._feed.refused(key, problem)

    def undeclare(self) -> None:
        """Stop the subscription, merge what already waits, stop the thread (evidence handed
        on later is merged on the caller's thread)."""
        self._sub.undeclare()
        if self._feed._merging is self:
            self._feed._merging = None
        self._waiting.put(None)
        self._thread.join(5.0)
