"""Whether the embedded store's files still hold what the store holds.

The store keeps the version and digest of each map it holds, and reads the map's file for each
get. A file edited by hand, truncated, emptied or removed under a running store was served as
it was found, with no word: ``rlutf map get`` printed walls no service localized on (or a
payload no tool could read, or nothing), and a restart then left every robot of the map with
``map_not_found`` and one log line that named neither the file nor what to do. The store now
serves a file only while it holds the version and content the store holds (checked once per
change of the file: its inode, size and modification time), and says once per change, with an
Event, which file no longer holds what and what to do; a put of the map repairs it.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path

from service.maps.book import Held, MapRejected

#: What identifies a file's content without reading it: inode, size, modification time (ns).
Signature = tuple[int, int, int]


def _signature(st: os.stat_result) -> Signature:
    return (st.st_ino, st.st_size, st.st_mtime_ns)


class FileCheck:
    """The signatures of the store's files known to hold what the store holds.

    Args:
        path: the file of a map id.
        check: the version and digest of a payload (raises :class:`MapRejected`).
        report: called with ``(map_id, message)`` once per change of a file that no longer
            holds what the store holds.
    """

    def __init__(
        self,
        path: Callable[[str], Path],
        check: Callable[[str, bytes], Held],
        report: Callable[[str, str], None],
    ) -> None:
        self._path = path
        self._check = check
        self._report = report
        self._good: dict[str, Signature] = {}
        self._said: dict[str, Signature | None] = {}
        self._lock = threading.Lock()

    def wrote(self, map_id: str) -> None:
        """The store wrote (or checked) the file of ``map_id``: it holds what is held."""
        try:
            sig = _signature(self._path(map_id).stat())
        except OSError:
            sig = None
        with self._lock:
            self._said.pop(map_id, None)
            if sig is None:
                self._good.pop(map_id, None)
            else:
                self._good[map_id] = sig

    def forget(self, map_id: str) -> None:
        """The map was removed."""
        with self._lock:
            self._good.pop(map_id, None)
            self._said.pop(map_id, None)

    def read(self, map_id: str, held: Callable[[], Held | None], say: bool = True) -> bytes | None:
        """The file's payload if it holds ``held()`` (version and digest, asked once the file
        is read: a put writes the file, then holds it), else ``None`` (said, unless ``say`` is
        false, once per change of the file).

        Raises:
            OSError: the file could not be read (other than missing).
        """
        path = self._path(map_id)
        try:
            with open(path, "rb") as f:
                sig: Signature | None = _signature(os.fstat(f.fileno()))
                data: bytes | None = f.read()
        except FileNotFoundError:
            sig, data = None, None
        with self._lock:
            if sig is not None and self._good.get(map_id) == sig:
                return data
            if sig is not None and self._said.get(map_id, ()) == sig:
                return None  # said already
        now = held()
        if now is None:
            return None
        what = self._differs(map_id, now, data)
        if what is None:
            if sig is not None:
                with self._lock:
                    self._good[map_id] = sig
                    self._said.pop(map_id, None)
            return data
        with self._lock:
            if self._said.get(map_id, ()) == sig or not say:
                return None
            self._said[map_id] = sig
        self._report(
            map_id,
            f"the map store's file {path} {what}, not version {now[0]} of map {map_id} the "
            "store holds (edited, damaged or removed on disk): the store no longer serves it, "
            "and a restart would load what the file holds (or nothing); the running services "
            f"keep their copy. Put the map again (`rlutf map put FILE --id {map_id}`), or put the "
            "file back as it was",
        )
        return None

    def repair(
        self, map_id: str, payload: bytes, held: Held, write: Callable[[str, bytes], None]
    ) -> bool:
        """A put of the very map held: ``write`` its payload if the file no longer holds it
        (``True`` then).

        Raises:
            OSError: from ``write``.
        """
        if self.read(map_id, lambda: held, say=False) is not None:
            return False
        write(map_id, payload)
        self.wrote(map_id)
        return True

    def _differs(self, map_id: str, held: Held, data: bytes | None) -> str | None:
        if data is None:
            return "is gone"
        try:
            found = self._check(map_id, data)
        except MapRejected as err:
            return f"holds no valid map ({err})"
        if found == held:
            return None
        return f"holds version {found[0]}" + (" with other content" if found[0] == held[0] else "")
