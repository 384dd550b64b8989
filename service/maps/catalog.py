"""The stored maps as a list, and the deliberate removal of one (a delete on its key).

Whatever storage holds ``{prefix}/maps/**`` answers: the service's embedded store, or zenohd's
storage manager. Nothing here prints; the command line shows what these return.
"""

from __future__ import annotations

import json
import time
from typing import Any, NamedTuple

import zenoh

from service.keys import KeyError_, Keys


class StoredMap(NamedTuple):
    """One map a storage answers for.

    Attributes:
        map_id: its id.
        version: its version (``None`` if the payload has none).
        size_bytes: its payload's size.
        extent: width and height of its bounding box, metres (``None`` if it has no
            coordinates).
    """

    map_id: str
    version: int | None
    size_bytes: int
    extent: tuple[float, float] | None


def _extent(geometry: Any) -> tuple[float, float] | None:
    xs: list[float] = []
    ys: list[float] = []

    def walk(node: Any) -> None:
        if (
            isinstance(node, list)
            and len(node) >= 2
            and all(isinstance(v, int | float) for v in node[:2])
        ):
            xs.append(float(node[0]))
            ys.append(float(node[1]))
        elif isinstance(node, list):
            for child in node:
                walk(child)

    if isinstance(geometry, dict):
        walk(geometry.get("coordinates"))
    if not xs:
        return None
    return max(xs) - min(xs), max(ys) - min(ys)


def describe(map_id: str, payload: bytes) -> StoredMap:
    """A stored map's id, version, size and extent (a payload that is not a map: no version)."""
    try:  # any client may answer on a map key: nested past any depth, say
        data = json.loads(payload)
        extent = _extent(data.get("geometry")) if isinstance(data, dict) else None
    except (ValueError, RecursionError):
        data = extent = None
    if not isinstance(data, dict):
        return StoredMap(map_id, None, len(payload), None)
    version = data.get("version")
    return StoredMap(map_id, version if isinstance(version, int) else None, len(payload), extent)


def list_maps(session: zenoh.Session, prefix: str, timeout: float) -> list[StoredMap]:
    """Every map the storages answer for on ``{prefix}/maps/*``, by id (the highest version of
    a map two storages answer for)."""
    keys = Keys(prefix)
    found: dict[str, StoredMap] = {}
    for reply in session.get(keys.map("*"), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            map_id = keys.parse_map_key(str(reply.ok.key_expr))
        except KeyError_:
            continue
        if map_id is None:
            continue
        entry = describe(map_id, reply.ok.payload.to_bytes())
        old = found.get(map_id)
        if old is None or (entry.version or 0) > (old.version or 0):
            found[map_id] = entry
    return [found[m] for m in sorted(found)]


def remove_map(session: zenoh.Session, prefix: str, map_id: str, timeout: float) -> bool:
    """Delete ``{prefix}/maps/{map_id}`` and wait until no storage answers for it.

    Returns:
        ``True`` once no storage answers for the map within ``timeout`` seconds of the delete.
    """
    key = Keys(prefix).map(map_id)
    session.delete(key)
    end = time.monotonic() + timeout
    while True:
        answered = any(r.ok is not None for r in session.get(key, timeout=min(timeout, 1.0)))
        if not answered:
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(0.1)
