"""The embedded, file-backed map storage.

A Zenoh storage is a subscriber that persists puts plus a ``complete`` queryable that answers
gets; zenoh-python ignores zenohd's plugin section, so the service hosts this one itself. Maps
are files ``{map_id}.json`` in one folder, written atomically (temporary file, fsync, rename,
fsync of the folder: :mod:`service.maps.files`), so a crash leaves either the old map or the new
one, never half of one.
Fleets that run zenohd's storage manager start the service with ``--no-store``.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from functools import partial

import zenoh

from rlutf.map import MapLimits
from schemas import StoredVersion, encode_answer, valid_id
from service.keys import KeyError_, Keys
from service.maps.book import (
    Held,
    MapChecker,
    MapRejected,
    VersionConflict,
    check_map,
    put_verdict,
)
from service.maps.filecheck import FileCheck
from service.maps.files import FileMapStore
from service.maps.readcache import ReadCache

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON

#: Map puts that may wait to be stored; a flood of puts beyond it is refused, with an Event.
_QUEUED = 16
#: Bytes of map puts that may wait to be stored (a put that arrives when none waits is always
#: taken, however large: the size limit is the check's to enforce).
_QUEUED_BYTES = 64 * 1024 * 1024
#: Seconds between two tries to write the maps held in memory only (the disk refused them).
RETRY_S = 5.0
#: The attachment of a get's reply served from memory (a map the disk refused so far): the
#: tools that put maps tell an operator the put is not durable yet.
UNWRITTEN_MARK = b"rlutf:unwritten"
#: Bytes of maps held in memory only at most; a put beyond them, which the disk also refuses, is
#: not taken (the old rule of a store that cannot write).
UNWRITTEN_BYTES = 256 * 1024 * 1024


def room_for(waiting: int, waiting_bytes: int, size: int, most: int, most_bytes: int) -> bool:
    """Whether a put of ``size`` bytes may wait behind ``waiting`` puts of ``waiting_bytes``:
    always when none waits (however large), else within ``most`` puts and ``most_bytes``."""
    return waiting == 0 or (waiting < most and waiting_bytes + size <= most_bytes)


def removed_conflict(map_id: str, version: int, removed: int) -> str:
    """The store's Event message for a put not newer than the version ``rlutf map remove``
    removed (read back by :func:`service.maps.client.removed_version`)."""
    return (
        f"map {map_id!r}: version {version} put, not newer than version {removed} that was "
        "removed (`rlutf map remove`), which running services may still hold; nothing changed "
        f"(put version {removed + 1} or later: rlutf map put --version next)"
    )


def stored_version(
    session: zenoh.Session, keys: Keys, map_id: str, timeout: float
) -> StoredVersion | None:
    """What the map store on the bus holds of ``map_id`` (the highest version if several stores
    answer), or ``None``: no store answers (zenohd's storage manager, which applies no version
    rule, answers nothing there; the embedded store answers for every map asked by its id)."""
    return stored_versions(session, keys, timeout, map_id).get(map_id)


def stored_versions(
    session: zenoh.Session, keys: Keys, timeout: float, map_id: str | None = None
) -> dict[str, StoredVersion]:
    """What the map stores on the bus hold of ``map_id``, or of every map one knows of (a get on
    ``{prefix}/mapversions/*``), by map id: the highest version if several stores answer."""
    key = keys.map_versions if map_id is None else keys.map_version(map_id)
    found: dict[str, StoredVersion] = {}
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            answer = StoredVersion.model_validate_json(reply.ok.payload.to_bytes())
        except ValueError:
            log.warning("bad map version answer on %s", reply.ok.key_expr)
            continue
        other = found.get(answer.map_id)
        if map_id in (None, answer.map_id) and (other is None or _beyond(answer, other)):
            found[answer.map_id] = answer
    return found


def _beyond(answer: StoredVersion, other: StoredVersion) -> bool:
    """Whether ``answer`` says more than ``other``: a higher version, or as high, more pending."""
    mine, theirs = answer.version, other.version
    if mine != theirs:
        return theirs is None or (mine is not None and mine > theirs)
    return answer.pending > other.pending


class MapStorage:
    """Serves a :class:`FileMapStore` on ``{prefix}/maps/**`` as a Zenoh storage.

    Puts are validated and stored on a thread of their own (a big map takes a while to
    validate; the Zenoh callback thread also carries the robots' inputs), in arrival order, by
    the rule every service follows (:func:`~service.maps.book.put_verdict`): a newer version is
    stored; an echo of the held version changes nothing; an older version, or the held version
    with other content, is not stored (the service that sees the same put reports the conflict).
    Invalid maps are not stored. Gets are answered from the files, so maps survive restarts.

    A map removed (``rlutf map remove``) leaves running services their copy and its version, so
    the store keeps the version removed (``.{map_id}.removed``): a later put must be newer than
    it, or be the removed version put back as it was, as for the services, and a refused one is
    reported here (``on_conflict``), since no service may hold the map to say so.

    Every service loads a put once this store holds it (:meth:`answer`; the services without
    it, the other processes of ``rlutf serve --processes`` and an instance started with
    ``--no-store``, ask :func:`stored_version` on ``{prefix}/mapversions/{map_id}``), and refuses
    what it refuses: a service without it that loaded the puts it saw loaded those this store
    dropped under a flood, and one started after a newer version was stored, or after a
    removal, held nothing to refuse an older put with.

    A newer version the disk refuses (full, read-only, the folder gone) is taken all the same
    and held in memory: every service on the bus loads a put as it sees it, so a store that did
    not take it would hold an older version than the running services, and a restart would
    switch robots back without anyone asking. Gets are answered with it, ``on_unwritten``
    reports it, and the store tries to write it every :data:`RETRY_S` seconds (and when it
    closes) until it can (``on_written``). At most :data:`UNWRITTEN_BYTES` are held so; a put
    beyond them is not taken (``on_drop`` says so).

    Args:
        session: the Zenoh session.
        keys: key layout.
        store: the files.
        max_bytes: the maps' size limit, bytes.
        on_error: reports a bad key or a map that could not be removed: ``(key, message)``.
        limits: extent and vertex limits of a map.
        checker: validates puts (the service's, so that a put is validated once).
        on_drop: reports a put not stored because too many already waited (default:
            ``on_error``).
        on_unwritten: reports a put the store could not write (a full disk; default:
            ``on_drop``), held in memory; past :data:`UNWRITTEN_BYTES`, ``on_drop`` says it
            was not taken.
        on_written: reports a map held in memory written at last (default: a log line).
        on_conflict: reports a put refused because a newer version of the map was removed
            (no running service may hold it to say so; default: a log line).
        on_claim: reports the store's folder replaced under it and claimed by another process
            (default: a log line).
        forward: called with every sample on ``{prefix}/maps/*`` this storage did not drop:
            the service beside it follows the maps so, and never loads a put its store dropped.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        store: FileMapStore,
        max_bytes: int,
        on_error: Callable[[str, str], None] | None = None,
        limits: MapLimits | None = None,
        checker: MapChecker | None = None,
        on_drop: Callable[[str, str], None] | None = None,
        forward: Callable[[zenoh.Sample], None] | None = None,
        on_unwritten: Callable[[str, str], None] | None = None,
        on_written: Callable[[str, str], None] | None = None,
        on_conflict: Callable[[str, str], None] | None = None,
        on_claim: Callable[[str, str], None] | None = None,
    ) -> None:
        self.store = store
        self.keys = keys
        self.max_bytes = max_bytes
        self.limits = limits
        self.checker = checker or MapChecker(max_bytes, limits)
        self.on_error = on_error or (lambda key, msg: None)
        self.on_drop = on_drop or self.on_error
        self.on_unwritten = on_unwritten or self.on_drop
        self.on_written = on_written or (lambda key, msg: log.info("%s", msg))
        self.on_conflict = on_conflict or (lambda key, msg: log.info("%s", msg))
        self.on_claim = on_claim or (lambda key, msg: log.warning("%s", msg))
        # Maps taken but not on disk yet: map id -> (payload, monotonic time of the first refusal)
        self._unwritten: dict[str, tuple[bytes, float]] = {}
        self._pending = 0  # puts queued or being stored
        self._pending_maps: dict[str, int] = {}  # the same, by map
        self._queued_bytes = 0
        self._queue_lock = threading.Lock()
        self.forward = forward
        self._forwarded = zenoh.KeyExpr(keys.maps)
        self._versions: dict[str, Held] = {}
        self.reads = ReadCache()  # the payloads read for gets, answered again for a moment
        # Held while the store's thread changes what it holds, never across a file write: the
        # Zenoh callbacks that answer gets read under it (the services ask for versions all the
        # time), and one that waited on a write held up the router's other links. The store's
        # thread alone changes what it holds, so it reads it without the lock.
        self._lock = threading.Lock()
        store.claim()  # the versions held below are this process's to keep
        # Maps removed (`rlutf map remove`): running services keep their copy, so a put must be
        # newer than the version removed for the store and them to agree.
        self._removed: dict[str, Held] = store.removed()
        self.files = FileCheck(store.path, self._check, self._file_changed)
        for map_id, payload in store.items():
            try:
                self._versions[map_id] = self._check(map_id, payload)
                self.files.wrote(map_id)
            except MapRejected as err:
                self.on_error(
                    self.keys.map(map_id),
                    f"the map store's file {store.path(map_id)} holds no valid map ({err}): "
                    f"map {map_id} is not served, and robots on it are not localized; put it "
                    f"again (`rlutf map put FILE --id {map_id}`), or put a valid file back and "
                    "restart",
                )
        self._said_claim: str | None = None
        self._tasks: queue.Queue[tuple[str, str, bytes | None] | None] = queue.Queue(_QUEUED)
        self._thread = threading.Thread(target=self._run, name="rlutf-store", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(keys.maps_storage, self._on_sample)
        self._queryable = session.declare_queryable(
            keys.maps_storage, self._on_query, complete=True
        )
        self._versions_queryable = session.declare_queryable(
            keys.map_versions, self._on_version_query
        )

    def _check(self, map_id: str, payload: bytes) -> Held:
        checked = check_map(
            payload, expected_id=map_id, max_bytes=self.max_bytes, limits=self.limits
        )
        return (checked.version, checked.digest)

    def _file_changed(self, map_id: str, message: str) -> None:
        self.on_error(self.keys.map(map_id), message)

    def _read(self, map_id: str) -> bytes | None:
        """The file of a map held, if it holds what is held (:class:`FileCheck`); while a
        put of it is stored, as it is."""
        with self._queue_lock:
            busy = map_id in self._pending_maps
        return self.store.get(map_id) if busy else self.files.read(map_id, self._stored(map_id))

    def _stored(self, map_id: str) -> Callable[[], Held | None]:
        return lambda: self._versions.get(map_id)

    def held(self, map_id: str) -> Held | None:
        """The version stored for ``map_id`` and its content digest, if any; for a map removed
        and not put since, the version removed (the rule's version to beat)."""
        with self._lock:
            return self._versions.get(map_id) or self._removed.get(map_id)

    def answer(self, map_id: str) -> StoredVersion:
        """What this store holds of ``map_id`` (:class:`StoredVersion`): asked before a service
        loads a put, and answered on ``{prefix}/mapversions/{map_id}``."""
        with self._queue_lock:
            pending = self._pending_maps.get(map_id, 0)
        with self._lock:
            stored = self._versions.get(map_id)
            held = stored or self._removed.get(map_id)
        version, digest = held if held is not None else (None, None)
        return StoredVersion(
            map_id=map_id,
            version=version,
            digest=digest,
            removed=stored is None and held is not None,
            pending=pending,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if (
            self._take(sample)
            and self.forward is not None
            and self._forwarded.intersects(sample.key_expr)
        ):
            self.forward(sample)

    def _take(self, sample: zenoh.Sample) -> bool:
        """Queue a put or a removal; ``False`` when it was dropped (too many wait)."""
        key = str(sample.key_expr)
        try:
            map_id = self.keys.parse_map_key(key)
        except KeyError_ as err:
            # The service it forwards to says invalid_key for it: one Event, not a second one
            # (invalid_map) from the store for the same put.
            if self.forward is None or not self._forwarded.intersects(sample.key_expr):
                self.on_error(key, str(err))
            return True
        if map_id is None:
            return True
        payload = None if sample.kind == zenoh.SampleKind.DELETE else sample.payload.to_bytes()
        size = 0 if payload is None else len(payload)
        with self._queue_lock:
            waiting = self._tasks.qsize()
            dropped = not room_for(waiting, self._queued_bytes, size, _QUEUED, _QUEUED_BYTES)
            held = self._queued_bytes / 1e6
            if not dropped:
                self._pending += 1
                self._pending_maps[map_id] = self._pending_maps.get(map_id, 0) + 1
                self._queued_bytes += size
                self._tasks.put_nowait((key, map_id, payload))
        if dropped:
            what = "removed" if payload is None else "stored"
            again = "remove" if payload is None else "put"
            self.on_drop(
                key,
                f"map {map_id} not {what}: {waiting} puts ({held:.1f} MB) already wait to be "
                f"stored; {again} it again",
            )
        return not dropped

    def busy(self) -> bool:
        """Whether puts wait to be stored, or one is being stored."""
        return self._pending > 0

    def _run(self) -> None:
        while True:
            try:
                task = self._tasks.get(timeout=RETRY_S)
            except queue.Empty:
                self._write_held()
                claim = self.store.reclaim()  # its folder replaced: claimed again, or said once
                if claim is not None and claim != self._said_claim:
                    self.on_claim(self.keys.events, claim)
                self._said_claim = claim
                continue
            if task is None:
                break
            try:
                self._apply(*task)
            except Exception:
                log.exception("storing %s failed", task[0])
            finally:
                with self._queue_lock:
                    self._pending -= 1
                    self._queued_bytes -= 0 if task[2] is None else len(task[2])
                    left = self._pending_maps.pop(task[1]) - 1
                    if left:
                        self._pending_maps[task[1]] = left
            del task  # the payload is not kept while the thread waits
        self._write_held()

    def unwritten(self) -> list[str]:
        """Ids of the maps held in memory only (their disk writes failed so far)."""
        with self._lock:
            return sorted(self._unwritten)

    def _write_held(self) -> None:
        """Try again to write the maps held in memory only (on the store's thread)."""
        for map_id, (payload, since) in list(self._unwritten.items()):
            try:
                self.store.put(map_id, payload)
            except OSError as err:
                log.debug("map %s still not written: %s", map_id, err)
                continue
            self.files.wrote(map_id)
            with self._lock:
                del self._unwritten[map_id]
            version = self._versions[map_id][0]
            self.on_written(
                self.keys.map(map_id),
                f"map {map_id} version {version} written to the store after "
                f"{time.monotonic() - since:.0f} s held in memory only",
            )

    def _apply(self, key: str, map_id: str, payload: bytes | None) -> None:
        """Store a put or a removal (on the store's thread)."""
        if payload is None:  # `rlutf map remove`: an operator's choice
            held = self._versions.get(map_id) or self._removed.get(map_id)
            try:
                self.store.delete(map_id, held)
            except OSError as err:
                self.on_error(key, f"could not remove map {map_id}: {err}")
                return
            self.files.forget(map_id)
            with self._lock:
                self._versions.pop(map_id, None)
                self._unwritten.pop(map_id, None)
                if held is not None:
                    self._removed[map_id] = held
            log.info("map %s removed", map_id)
            return
        try:
            version, digest, _ = self.checker.check(map_id, payload)
        except MapRejected:
            return  # the service's map subscriber reports it
        held = self._versions.get(map_id)
        removed = None if held is not None else self._removed.get(map_id)
        verdict = put_verdict(held or removed, version, digest)
        if removed is not None and verdict != "conflict":
            verdict = "new"  # the removed version put back as it was, or a newer one
        if verdict == "echo" and held is not None and map_id not in self._unwritten:
            try:  # a put of the very map held writes its file again if it no longer holds it
                if self.files.repair(map_id, payload, held, self.store.put):
                    self.on_written(key, f"map {map_id} version {held[0]} written again")
            except OSError as err:
                self._file_changed(map_id, f"map {map_id}: its file could not be written: {err}")
        if verdict != "new":
            if removed is not None:  # no running service may know of the removal
                self.on_conflict(key, removed_conflict(map_id, version, removed[0]))
            elif held is not None and verdict == "conflict":
                log.info("%s", VersionConflict(map_id, version, held[0]))
            return
        try:
            self.store.put(map_id, payload)
        except OSError as err:  # a full disk: held in memory, written when it can be
            self._hold_unwritten(key, map_id, payload, (version, digest), err)
            return
        self.files.wrote(map_id)
        with self._lock:
            self._unwritten.pop(map_id, None)  # an older version waiting is superseded
            self._versions[map_id] = (version, digest)
            unmark = self._removed.pop(map_id, None) is not None
        if unmark:
            try:
                self.store.unmark(map_id)
            except OSError as err:  # the mark stays: its version is older than this one's
                log.warning("map %s: removal mark left: %s", map_id, err)

    def _hold_unwritten(
        self, key: str, map_id: str, payload: bytes, held: Held, err: OSError
    ) -> None:
        """A newer version the disk refused: held in memory (within :data:`UNWRITTEN_BYTES`),
        or, past that, not taken (on the store's thread)."""
        waiting = sum(len(p) for m, (p, _) in self._unwritten.items() if m != map_id)
        if waiting + len(payload) > UNWRITTEN_BYTES:
            self.on_drop(
                key,
                f"map {map_id} version {held[0]} not stored: the store could not write it "
                f"({err}) and holds {waiting / 1e6:.0f} MB of maps it could not write already; "
                "put it again once it can write",
            )
            return
        since = self._unwritten.get(map_id, (b"", time.monotonic()))[1]
        with self._lock:
            self._unwritten[map_id] = (payload, since)
            self._versions[map_id] = held
        self.on_unwritten(
            key,
            f"map {map_id} version {held[0]} taken but not written: the store could not write "
            f"it ({err}); it serves it from memory and tries again every {RETRY_S:g} s (a "
            "restart before then loses it)",
        )

    def _on_query(self, query: zenoh.Query) -> None:
        with query:
            ke = query.key_expr
            with self._lock:
                held = dict(self._versions)
                memory = {m: p for m, (p, _) in self._unwritten.items()}
            for map_id, version in held.items():
                key = self.keys.map(map_id)
                if ke.intersects(zenoh.KeyExpr(key)):
                    payload = memory.get(map_id)
                    if payload is not None:
                        query.reply(key, payload, encoding=JSON, attachment=UNWRITTEN_MARK)
                        continue
                    try:
                        read = self.reads.payload(map_id, version, partial(self._read, map_id))
                    except OSError as err:  # its folder gone or unreadable: nothing to answer
                        log.warning("map %s could not be read from the store: %s", map_id, err)
                        continue
                    if read is not None:
                        query.reply(key, read, encoding=JSON)

    def _on_version_query(self, query: zenoh.Query) -> None:
        """Answer ``{prefix}/mapversions/*``: for each map asked for that this store holds,
        removed or has puts of to store, and for a map asked by its id in any case, what it
        holds of it (:class:`StoredVersion`; nothing held: a null version). A service that asks
        before it loads a put so tells a store that dropped the put from no store at all."""
        with query:
            ke = query.key_expr
            asked = str(ke).rpartition("/")[2]
            with self._queue_lock:
                known = set(self._pending_maps)
            with self._lock:
                known |= set(self._versions) | set(self._removed)
            if valid_id(asked) and str(ke) == self.keys.map_version(asked):
                known.add(asked)
            for map_id in sorted(known):
                key = self.keys.map_version(map_id)
                if ke.intersects(zenoh.KeyExpr(key)):
                    answer = encode_answer(self.answer(map_id))
                    query.reply(key, answer, encoding=JSON)

    def close(self) -> None:
        """Stop serving (after the puts already received are stored)."""
        self._sub.undeclare()
        self._queryable.undeclare()
        self._versions_queryable.undeclare()
        self._tasks.put(None)
        self._thread.join(10.0)
        self.store.release()
