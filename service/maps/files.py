"""The embedded map store's files: one ``{map_id}.json`` per map in one folder, written
atomically (temporary file, fsync, rename, fsync of the folder), so a crash leaves either the old
map or the new one, never half of one; the versions of removed maps beside them; and the folder's
claim by the one process that serves it (:class:`service.maps.store.MapStorage`).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from schemas import valid_id
from service.infile import replace_durably, sync_folder
from service.maps.book import Held

log = logging.getLogger(__name__)


class MapStore(Protocol):
    """Persistence of map payloads by id."""

    def get(self, map_id: str) -> bytes | None:
        """The stored payload, or ``None``."""

    def put(self, map_id: str, payload: bytes) -> None:
        """Store a payload, replacing any other."""

    def delete(self, map_id: str, held: Held | None = None) -> None:
        """Forget a map (remembering the version ``held`` removed)."""

    def ids(self) -> list[str]:
        """Every stored id."""


#: A removed map's version is kept in ``.{map_id}.removed`` (JSON: version and digest).
REMOVED_SUFFIX = ".removed"

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

    def claim(self) -> bool:
        """Serve this folder alone: hold its :data:`CLAIM_FILE` locked until :meth:`release`
        (or this process ends, when the system lets the lock go by itself).

        Two services on one folder (a second site or a test instance started from the same
        working directory, each with the default ``--store store``) each checked map versions
        against what they had read at their start, and each overwrote the other's files: a
        site's map replaced by another site's of the same id at its next restart. Readers (the
        CLI reading a map from a folder) do not claim it. A file system that refuses locks
        (some network mounts) is served unclaimed.

        Returns:
            Whether the folder is locked (not on such a file system).

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
            return False
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._claim = fd
        return True

    def reclaim(self) -> str | None:
        """Claim the folder again when its :data:`CLAIM_FILE` is no longer the one held: the
        folder was removed and made again, or replaced by a copy, under the running store, and
        a second ``rlutf serve`` on it was let in (it found no claim). ``None`` when it is held
        again (or cannot be: the folder gone, whose writes fail and say so); else what is wrong.
        """
        old = self._claim
        if old is None:
            return None
        try:
            held, found = os.fstat(old), (self.root / CLAIM_FILE).stat()
            if (held.st_dev, held.st_ino) == (found.st_dev, found.st_ino):
                return None
        except FileNotFoundError:
            if not self.root.is_dir():
                return None
        self._claim = None
        try:
            claimed = self.claim()
        except StoreInUse as err:
            self._claim = old
            return f"{err}; this process serves it too (the folder was replaced under it): stop one"
        if not claimed:  # not locked: keep the old claim
            self._claim = old
            return None
        os.close(old)
        log.info("map store %s: claimed again (the folder was replaced)", self.root)
        return None

    def release(self) -> None:
        """Let the folder go (:meth:`claim`)."""
        if self._claim is not None:
            os.close(self._claim)
            self._claim = None

    def path(self, map_id: str) -> Path:
        """The file of ``map_id`` (raises ``ValueError`` for an invalid id)."""
        return self._path(map_id)

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
            replace_durably(path, payload, f".{map_id}.")

    def _mark(self, map_id: str) -> Path:
        return self._path(map_id).with_name(f".{map_id}{REMOVED_SUFFIX}")

    def delete(self, map_id: str, held: Held | None = None) -> None:
        """Remove the file if present, durably (a crash does not bring the map back); with
        ``held``, remember the version removed (:meth:`removed`)."""
        path = self._path(map_id)
        with self._lock:
            if held is not None:
                mark = json.dumps({"version": held[0], "digest": held[1]}).encode()
                replace_durably(self._mark(map_id), mark, f".{map_id}.")
            if path.exists():
                path.unlink(missing_ok=True)
                sync_folder(self.root)

    def removed(self) -> dict[str, Held]:
        """The versions of the maps removed and not put since (:meth:`delete`), by id."""
        out: dict[str, Held] = {}
        for mark in self.root.glob(f".*{REMOVED_SUFFIX}"):
            map_id = mark.name[1 : -len(REMOVED_SUFFIX)]
            try:
                data = json.loads(mark.read_bytes())
                out[map_id] = (int(data["version"]), str(data["digest"]))
            except (OSError, ValueError, KeyError, TypeError) as err:
                log.warning("map store: %s unreadable, ignored: %s", mark, err)
        return {k: v for k, v in out.items() if valid_id(k)}

    def unmark(self, map_id: str) -> None:
        """Forget a removed map's version (a newer one was put)."""
        with self._lock:
            mark = self._mark(map_id)
            if mark.exists():
                mark.unlink(missing_ok=True)
                sync_folder(self.root)

    def ids(self) -> list[str]:
        """Ids of the stored maps, sorted."""
        return sorted(p.stem for p in self.root.glob("*.json") if valid_id(p.stem))

    def items(self) -> Iterator[tuple[str, bytes]]:
        """Every stored ``(map_id, payload)``."""
        for map_id in self.ids():
            payload = self.get(map_id)
            if payload is not None:
                yield map_id, payload
