"""The embedded, file-backed map storage.

A Zenoh storage is a subscriber that persists puts plus a ``complete`` queryable that answers
gets; zenoh-python ignores zenohd's plugin section, so the service hosts this one itself. Maps
are files ``{map_id}.json`` in one folder, written atomically (temporary file, fsync, rename,
fsync of the folder), so a crash leaves either the old map or the new one, never half of one.
Fleets that run zenohd's storage manager start the service with ``--no-store``.
"""

from __future__ import annotations

import logging
import os
import queue
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

import zenoh

from rlutf.map import MapLimits
from schemas import valid_id
from service.keys import KeyError_, Keys
from service.maps.book import (
    Held,
    MapChecker,
    MapRejected,
    VersionConflict,
    check_map,
    put_verdict,
)

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


class MapStore(Protocol):
    """Persistence of map payloads by id."""

    def get(self, map_id: str) -> bytes | None:
        """The stored payload, or ``None``."""

    def put(self, map_id: str, payload: bytes) -> None:
        """Store a payload, replacing any other."""

    def delete(self, map_id: str) -> None:
        """Forget a map."""

    def ids(self) -> list[str]:
        """Every stored id."""


#: The file in a store's folder that its serving process holds locked (``flock``), with its pid.
CLAIM_FILE = ".rlutf-store.lock"


class StoreInUse(RuntimeError):
    """Another running process serves the store's folder."""


class FileMapStore:
    """Maps as JSON files in one folder.

    Args:
        root: the folder; created if missing.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._claim: int | None = None

    def claim(self) -> None:
        """Serve this folder alone: hold its :data:`CLAIM_FILE` locked until :meth:`release`
        (or this process ends, when the system lets the lock go by itself).

        Two services on one folder (a second site or a test instance started from the same
        working directory, each with the default ``--store store``) each checked map versions
        against what they had read at their start, and each overwrote the other's files: a
        site's map replaced by another site's of the same id at its next restart. Readers (the
        CLI reading a map from a folder) do not claim it. A file system that refuses locks
        (some network mounts) is served unclaimed.

        Raises:
            StoreInUse: another process holds the folder (the message names its pid).
        """
        import fcntl

        path = self.root / CLAIM_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise StoreInUse(
                f"the map store folder {self.root} is served by another running process (pid "
                f"{holder}: another `rlutf serve`?)"
            ) from None
        except OSError as err:
            os.close(fd)
            log.warning("map store %s: not locked (%s): serve it from one process only", path, err)
            return
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._claim = fd

    def release(self) -> None:
        """Let the folder go (:meth:`claim`)."""
        if self._claim is not None:
            os.close(self._claim)
            self._claim = None

    def _path(self, map_id: str) -> Path:
        if not valid_id(map_id):
            raise ValueError(f"invalid map id {map_id!r}")
        return self.root / f"{map_id}.json"

    def get(self, map_id: str) -> bytes | None:
        """The stored payload, or ``None``."""
        try:
            return self._path(map_id).read_bytes()
        except FileNotFoundError:
            return None

    def put(self, map_id: str, payload: bytes) -> None:
        """Write atomically: a crash leaves the old file or the new one."""
        path = self._path(map_id)
        with self._lock:
            fd, tmp = tempfile.mkstemp(prefix=f".{map_id}.", suffix=".tmp", dir=self.root)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(payload)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            dir_fd = os.open(self.root, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)

    def delete(self, map_id: str) -> None:
        """Remove the file if present, durably (a crash does not bring the map back)."""
        path = self._path(map_id)
        with self._lock:
            if path.exists():
                path.unlink(missing_ok=True)
                self._sync_folder()

    def _sync_folder(self) -> None:
        dir_fd = os.open(self.root, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)

    def ids(self) -> list[str]:
        """Ids of the stored maps, sorted."""
        return sorted(p.stem for p in self.root.glob("*.json") if valid_id(p.stem))

    def items(self) -> Iterator[tuple[str, bytes]]:
        """Every stored ``(map_id, payload)``."""
        for map_id in self.ids():
            payload = self.get(map_id)
            if payload is not None:
                yield map_id, payload


class MapStorage:
    """Serves a :class:`FileMapStore` on ``{prefix}/maps/**`` as a Zenoh storage.

    Puts are validated and stored on a thread of their own (a big map takes a while to
    validate; the Zenoh callback thread also carries the robots' inputs), in arrival order, by
    the rule every service follows (:func:`~service.maps.book.put_verdict`): a newer version is
    stored; an echo of the held version changes nothing; an older version, or the held version
    with other content, is not stored (the service that sees the same put reports the conflict).
    Invalid maps are not stored. Gets are answered from the files, so maps survive restarts.

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
        # Maps taken but not on disk yet: map id -> (payload, monotonic time of the first refusal)
        self._unwritten: dict[str, tuple[bytes, float]] = {}
        self._pending = 0  # puts queued or being stored
        self._queued_bytes = 0
        self._queue_lock = threading.Lock()  # not _lock, which a file write holds
        self.forward = forward
        self._forwarded = zenoh.KeyExpr(keys.maps)
        self._versions: dict[str, Held] = {}
        self._lock = threading.Lock()
        store.claim()  # the versions held below are this process's to keep
        for map_id, payload in store.items():
            try:
                checked = check_map(payload, expected_id=map_id, max_bytes=max_bytes, limits=limits)
                self._versions[map_id] = (checked.version, checked.digest)
            except MapRejected as err:
                log.warning("stored map %s is invalid and is not served: %s", map_id, err)
        self._tasks: queue.Queue[tuple[str, str, bytes | None] | None] = queue.Queue(_QUEUED)
        self._thread = threading.Thread(target=self._run, name="rlutf-store", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(keys.maps_storage, self._on_sample)
        self._queryable = session.declare_queryable(
            keys.maps_storage, self._on_query, complete=True
        )

    def held(self, map_id: str) -> Held | None:
        """The version stored for ``map_id`` and its content digest, if any."""
        with self._lock:
            return self._versions.get(map_id)

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
                task = self._tasks.get(timeout=RETRY_S if self._unwritten else None)
            except queue.Empty:
                self._write_held()
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
            del task  # the payload is not kept while the thread waits
        self._write_held()

    def unwritten(self) -> list[str]:
        """Ids of the maps held in memory only (their disk writes failed so far)."""
        with self._lock:
            return sorted(self._unwritten)

    def _write_held(self) -> None:
        """Try again to write the maps held in memory only."""
        with self._lock:
            for map_id, (payload, since) in list(self._unwritten.items()):
                try:
                    self.store.put(map_id, payload)
                except OSError as err:
                    log.debug("map %s still not written: %s", map_id, err)
                    continue
                del self._unwritten[map_id]
                version = self._versions[map_id][0]
                self.on_written(
                    self.keys.map(map_id),
                    f"map {map_id} version {version} written to the store after "
                    f"{time.monotonic() - since:.0f} s held in memory only",
                )

    def _apply(self, key: str, map_id: str, payload: bytes | None) -> None:
        if payload is None:  # `rlutf map remove`: an operator's choice
            with self._lock:
                try:
                    self.store.delete(map_id)
                except OSError as err:
                    self.on_error(key, f"could not remove map {map_id}: {err}")
                    return
                self._versions.pop(map_id, None)
                self._unwritten.pop(map_id, None)
            log.info("map %s removed", map_id)
            return
        try:
            version, digest, _ = self.checker.check(map_id, payload)
        except MapRejected:
            return  # the service's map subscriber reports it
        with self._lock:
            held = self._versions.get(map_id)
            verdict = put_verdict(held, version, digest)
            if verdict != "new":
                if held is not None and verdict == "conflict":
                    log.info("%s", VersionConflict(map_id, version, held[0]))
                return
            try:
                self.store.put(map_id, payload)
            except OSError as err:  # a full disk: held in memory, written when it can be
                self._hold_unwritten(key, map_id, payload, (version, digest), err)
                return
            self._unwritten.pop(map_id, None)  # an older version waiting is superseded
            self._versions[map_id] = (version, digest)

    def _hold_unwritten(
        self, key: str, map_id: str, payload: bytes, held: Held, err: OSError
    ) -> None:
        """A newer version the disk refused: held in memory (within :data:`UNWRITTEN_BYTES`),
        or, past that, not taken. Called with ``_lock`` held."""
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
                held = list(self._versions)
                memory = {m: p for m, (p, _) in self._unwritten.items()}
            for map_id in held:
                key = self.keys.map(map_id)
                if ke.intersects(zenoh.KeyExpr(key)):
                    payload = memory.get(map_id)
                    if payload is not None:
                        query.reply(key, payload, encoding=JSON, attachment=UNWRITTEN_MARK)
                        continue
                    try:
                        payload = self.store.get(map_id)
                    except OSError as err:  # its folder gone or unreadable: nothing to answer
                        log.warning("map %s could not be read from the store: %s", map_id, err)
                        continue
                    if payload is not None:
                        query.reply(key, payload, encoding=JSON)

    def close(self) -> None:
        """Stop serving (after the puts already received are stored)."""
        self._sub.undeclare()
        self._queryable.undeclare()
        self._tasks.put(None)
        self._thread.join(10.0)
        self.store.release()
