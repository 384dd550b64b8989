"""Client tools over Zenoh for maps: put a map file into the store, get a stored map."""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from schemas import Event, EventCode, Map, SchemaError, decode, encode, valid_id
from service.infile import read_regular
from service.keys import Keys
from service.maps.book import (
    FILE_MAX_BYTES,
    MapRejected,
    content_digest,
    load_map,
    put_verdict,
)
from service.maps.store import UNWRITTEN_MARK, stored_version

JSON = zenoh.Encoding.APPLICATION_JSON


def map_message_from_file(path: Path, map_id: str | None, version: int | None) -> bytes:
    """A Map payload from a file holding a Map message or a bare GeoJSON geometry.

    Raises:
        ValueError: unreadable file, bad JSON, invalid id or invalid map (message says why).
    """
    try:
        text = read_regular(path, FILE_MAX_BYTES).decode("utf-8-sig")  # a BOM is no matter
        data: Any = json.loads(text)
    except OSError as err:
        raise ValueError(f"cannot read {path}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text, so no JSON{import_hint(path)}") from err
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: malformed JSON: {err}{import_hint(path)}") from err
    except RecursionError:
        raise ValueError(f"{path}: JSON nested deeper than a Map can be") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    data = unwrap_geojson(path, data)
    mid = map_id or data.get("map_id") or path.stem.split(".")[0]
    if not valid_id(str(mid)):
        raise ValueError(f"map id {mid!r} does not match [A-Za-z0-9_-]{{1,64}}; use --id")
    data["map_id"] = mid
    data["version"] = version if version is not None else data.get("version", 1)
    data.setdefault("frame_id", "map")
    try:
        msg = decode(Map, json.dumps(data), max_bytes=FILE_MAX_BYTES)
        payload = encode(msg)
        load_map(payload, expected_id=str(mid), max_bytes=len(payload))
    except (SchemaError, MapRejected) as err:
        raise ValueError(f"{path}: invalid map: {err}") from err
    return payload


def import_hint(path: Path, then: str = "--put") -> str:
    """For a file that looks like a map_server map (its YAML or image), how to import it and
    ``then`` (``--put``: into the store; ``--png X``: drawn); else ``""``."""
    if path.suffix.lower() in (".yaml", ".yml", ".pgm", ".png"):
        return (
            f"; a map_server map (YAML and image) is imported with rlutf map import "
            f"{path.with_suffix('.yaml')} {then}"
        )
    return ""


def unwrap_geojson(path: Path, data: dict[str, Any]) -> dict[str, Any]:
    """A map file's JSON object as a Map's fields: a bare GeoJSON geometry, a Feature or a
    FeatureCollection (:func:`collection_geometry`) becomes ``{"geometry": ...}``; anything
    else (a Map message) is returned as it is.

    Raises:
        ValueError: a FeatureCollection that holds no map (why).
    """
    kind = data.get("type")
    if kind in ("Polygon", "MultiPolygon"):
        return {"geometry": data}
    if kind == "Feature":
        return {"geometry": data.get("geometry")}
    if kind == "FeatureCollection":
        return {"geometry": collection_geometry(path, data)}
    return data


def collection_geometry(path: Path, data: dict[str, Any]) -> dict[str, Any]:
    """The geometry of a GeoJSON FeatureCollection of polygons (what geojson.io and QGIS
    export): one Polygon feature's own, else a MultiPolygon of every feature's polygons, as
    given (the map's checks then refuse polygons that overlap).

    Raises:
        ValueError: no feature, or a feature that is not a Polygon or MultiPolygon (named).
    """
    features = data.get("features")
    if not isinstance(features, list) or not features:
        raise ValueError(f"{path}: a FeatureCollection with no features: no map in it")
    polygons: list[Any] = []
    for k, feature in enumerate(features, 1):
        geometry = feature.get("geometry") if isinstance(feature, dict) else None
        kind = geometry.get("type") if isinstance(geometry, dict) else None
        if kind == "Polygon":
            polygons.append(geometry["coordinates"])  # type: ignore[index]
        elif kind == "MultiPolygon" and isinstance(geometry["coordinates"], list):  # type: ignore[index]
            polygons.extend(geometry["coordinates"])  # type: ignore[index]
        else:
            raise ValueError(
                f"{path}: feature {k} of {len(features)} is a {kind or 'feature without geometry'}"
                ": a map is the free space as Polygon or MultiPolygon features (walls are their "
                "boundaries, obstacles their holes)"
            )
    if len(polygons) == 1:
        return {"type": "Polygon", "coordinates": polygons[0]}
    return {"type": "MultiPolygon", "coordinates": polygons}


NEXT = "next"
"""``--version next``: the version the store holds plus one (1 when it holds none)."""


def parse_version(text: str) -> int | str:
    """``--version``: a positive integer or ``next``."""
    if text == NEXT:
        return NEXT
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a version >= 1 or 'next', got {text!r}")
    return value


def held_map(
    session: zenoh.Session, key: str, timeout: float, unless: bytes | None = None
) -> Map | bytes | None:
    """The map a storage answers for ``key``, or ``None`` when none answers; ``unless`` itself
    (not decoded: a map of real size takes seconds) when the storage answers with those bytes.
    """
    return held_reply(session, key, timeout, unless)[0]


def held_reply(
    session: zenoh.Session, key: str, timeout: float, unless: bytes | None = None
) -> tuple[Map | bytes | None, bool]:
    """:func:`held_map`, and whether the storage holds it in memory only (the embedded store
    could not write it to disk yet: its reply carries :data:`~service.maps.store.UNWRITTEN_MARK`).
    """
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        payload = reply.ok.payload.to_bytes()
        mark = reply.ok.attachment
        unwritten = mark is not None and mark.to_bytes() == UNWRITTEN_MARK
        if unless is not None and payload == unless:
            return unless, unwritten
        try:
            return decode(Map, payload, max_bytes=FILE_MAX_BYTES), unwritten
        except SchemaError:
            continue
    return None, False


def put_map(
    session: zenoh.Session,
    prefix: str,
    path: Path,
    map_id: str | None,
    version: int | str | None = NEXT,
    timeout: float = 5.0,
) -> int:
    """Put a map file into whatever storage holds ``{prefix}/maps/**`` and wait for its answer.

    Args:
        session: a session on the bus.
        prefix: key prefix.
        path: a Map message or GeoJSON geometry.
        map_id: the id (default: the file's, else its stem).
        version: a version, :data:`NEXT` (the held version plus one) or ``None`` (the file's).
        timeout: how long to wait for the store, seconds.

    Returns:
        0 when the store holds the map put (or already held it), or with ``timeout`` 0 when
        it was put (nothing is asked, so it is not confirmed); 2 for a file that is unreadable
        or no valid map (the input to fix, as every command's exit code 2); 1 when the put
        failed: a version the store refuses (the message names the version it holds and what
        to do), or no storage answering.
    """
    explicit = version if isinstance(version, int) else None
    try:
        payload = map_message_from_file(path, map_id, explicit)
    except ValueError as err:
        print(f"rlutf map put: {err}", file=sys.stderr)
        return 2
    if timeout == 0 and version != NEXT:  # next needs the store's answer: it is asked
        msg = decode(Map, payload, max_bytes=len(payload))
        key = Keys(prefix).map(msg.map_id)
        session.put(key, payload, encoding=JSON)
        print(
            f"put {key} (version {msg.version}, {len(payload)} bytes): not confirmed, --timeout "
            f"0 waits for no answer (`rlutf map get {msg.map_id}` shows what the store holds)"
        )
        return 0
    put = put_payload(session, prefix, payload, NEXT if version == NEXT else None, timeout)
    if put.stored:
        print(put.said)
        return 0
    print(f"rlutf map put: {put.said}", file=sys.stderr)
    return 1


@dataclass(frozen=True)
class Put:
    """What became of a map put: whether the store holds it, as which version, whether this put
    stored it (rather than finding it held already), and the line that says so (the reason,
    when the store does not hold it)."""

    stored: bool
    version: int | None
    said: str
    new: bool = False


def put_payload(
    session: zenoh.Session,
    prefix: str,
    payload: bytes,
    version: str | None = NEXT,
    timeout: float = 5.0,
) -> Put:
    """Put a valid Map payload into the store and wait for its answer (:func:`put_map`).

    ``version``: :data:`NEXT` puts it as the held version plus one, unless the store holds the
    same walls already; ``None`` as the payload's own version.
    """
    msg = decode(Map, payload, max_bytes=len(payload))
    key = Keys(prefix).map(msg.map_id)
    found, in_memory = held_reply(session, key, timeout)
    held = found if isinstance(found, Map) else None
    if version == NEXT:
        if held is not None and _same_content(held, msg):
            said = f"unchanged: {key} already holds this map as version {held.version}"
            return _unchanged(key, held.version, said, in_memory)
        stored = None if held is not None else stored_version(session, Keys(prefix), msg.map_id, 1)
        if stored is not None and stored.version is not None and not stored.removed:
            # held but not served (its file damaged): the very map held repairs it, else next
            put_as = msg.model_copy(update={"version": stored.version})
            if content_digest(put_as) != stored.digest:
                put_as = msg.model_copy(update={"version": stored.version + 1})
            return _put(session, prefix, key, put_as, None, in_memory, timeout)
        msg = msg.model_copy(update={"version": held.version + 1 if held is not None else 1})
        put = _put(session, prefix, key, msg, held, in_memory, timeout)
        named = None if put.stored or held is not None else held_named(put.said)
        if named is None:
            return put
        # Nothing stored, yet a version is held: the map was removed (`rlutf map remove`) at a
        # version the store and the running services keep. Next is the one after it.
        msg = msg.model_copy(update={"version": named + 1})
    return _put(session, prefix, key, msg, held, in_memory, timeout)


def held_named(said: str) -> int | None:
    """The version a refusal of a put names as held (the store's of a version not newer than
    one removed, :func:`service.maps.store.removed_conflict`, or a running service's
    :class:`~service.maps.book.VersionConflict`), if ``said`` is such a refusal."""
    found = re.search(r"(?:not newer than version|than the held version) (\d+)", said)
    return int(found[1]) if found else None


def _put(
    session: zenoh.Session,
    prefix: str,
    key: str,
    msg: Map,
    held: Map | None,
    in_memory: bool,
    timeout: float,
) -> Put:
    """Put ``msg`` as it is (its version chosen) and wait for the store's answer."""
    payload = encode(msg)
    if held is not None:
        verdict = put_verdict(
            (held.version, content_digest(held)), msg.version, content_digest(msg)
        )
        if verdict == "echo":
            said = f"unchanged: {key} already holds version {msg.version} with this content"
            return _unchanged(key, msg.version, said, in_memory)
        if verdict == "conflict":
            return Put(False, held.version, _refused(key, msg.version, held.version))
    refused: list[Event] = []  # the store's Events about this put (it could not take it)
    verdicts: list[Event] = []  # the running services' (loaded it, or refused it)

    def on_event(sample: zenoh.Sample) -> None:
        try:
            ev = decode(Event, sample.payload.to_bytes())
        except SchemaError:
            return
        if ev.key == key and ev.code in _REFUSALS:
            refused.append(ev)
        if ev.key == key and ev.code in _VERDICTS:
            verdicts.append(ev)

    watch = session.declare_subscriber(Keys(prefix).events, on_event)
    try:
        services = _live_services(session, prefix, min(timeout, 1.0))
        deadline = time.monotonic() + timeout
        session.put(key, payload, encoding=JSON)
        put = _confirm(session, key, msg, payload, timeout, refused)
        if put.stored and put.new:
            return _services_took(put, key, services, verdicts, deadline)
        return put
    finally:
        watch.undeclare()


#: The store's Events that say a put is not (durably) stored (a conflict here: a version not
#: newer than one removed, which the tool cannot see before it puts).
_REFUSALS = (
    EventCode.MAP_DROPPED,
    EventCode.INVALID_MAP,
    EventCode.MAP_WRITE_FAILED,
    EventCode.MAP_VERSION_CONFLICT,
)
#: A running service's Events that say what it made of a map put (unchanged: it held it).
_VERDICTS = (EventCode.MAP_UPDATED, EventCode.MAP_VERSION_CONFLICT, EventCode.MAP_UNCHANGED)


def _live_services(session: zenoh.Session, prefix: str, timeout: float) -> int:
    """How many service instances are live (liveliness tokens on ``{prefix}/service/*``)."""
    replies = session.liveliness().get(Keys(prefix).all_services, timeout=timeout)
    return len({str(r.ok.key_expr) for r in replies if r.ok is not None})


def _services_took(
    put: Put, key: str, services: int, verdicts: list[Event], deadline: float
) -> Put:
    """A put the store holds, and what the running services made of it: a service that holds a
    newer version refuses it (``map_version_conflict``). The store keeps a removed map's version
    (:mod:`service.maps.files`), so the two agree after ``rlutf map remove``; they can still
    disagree where a service holds a version the store never had or lost (a store folder
    replaced under a running fleet). Waits until each live service has said (or the deadline); a
    service that already held this very map (a map removed and put back as it was) says so
    (``map_unchanged``): before, it said nothing, and the tool waited its whole timeout.

    A service says ``map_unchanged`` and ``map_version_conflict`` once per map every
    ``event_interval_s`` (:mod:`service.live.throttle`); one held back goes out when the
    interval ends, so the word on this put comes then at the latest. Words are told apart by
    the map's key and the code, not by put: other clients' puts of the map at the same time
    count too, as they did before."""
    while len(verdicts) < services and time.monotonic() < deadline:
        time.sleep(0.05)
    conflict = next((e for e in verdicts if e.code == EventCode.MAP_VERSION_CONFLICT), None)
    if conflict is None:
        if verdicts and all(e.code == EventCode.MAP_UNCHANGED for e in verdicts):
            said = f"{put.said}; the running services already held it: nothing changed for them"
            return Put(True, put.version, said, new=True)
        return put
    held = held_named(conflict.message)
    fix = (
        f"put it as version {held + 1} with --version {held + 1}"
        if held is not None
        else "put it again with a --version above the one that service holds"
    )
    return Put(
        False,
        put.version,
        f"the store took {key} as version {put.version}, but a running service refused it "
        f"({conflict.message}): it holds a newer version than the store did: {fix}, which the "
        "store and the services both take",
        new=True,
    )


def _stores_own(ev: Event) -> bool:
    """Whether a refusal on the map's key is the store's: a conflict is the store's only when it
    names a removed version (:func:`service.maps.store.removed_conflict`)."""
    return ev.code != EventCode.MAP_VERSION_CONFLICT or "that was removed" in ev.message


def _unchanged(key: str, version: int, said: str, in_memory: bool) -> Put:
    """A put that changes nothing: done, unless the store holds the map in memory only."""
    if not in_memory:
        return Put(True, version, said)
    return Put(False, version, f"{said}, in memory only: {_NOT_WRITTEN}")


#: What a put held in memory only means (the embedded store could not write it to disk).
_NOT_WRITTEN = (
    "the store could not write it to disk (full, read-only, or its folder gone; Event "
    "map_write_failed: `rlutf events`); the running services use it and the store tries to write "
    "it every 5 s, but a restart of the store before then loses it"
)


def _same_content(held: Map, msg: Map) -> bool:
    return content_digest(held) == content_digest(msg.model_copy(update={"version": held.version}))


def _refused(key: str, version: int, held: int) -> str:
    return (
        f"{key} holds version {held}; version {version} was not stored (a lower version, or "
        f"the same version with other content, changes nothing). Put it as version "
        f"{held + 1} with --version {held + 1}, or --version next."
    )


def _confirm(
    session: zenoh.Session,
    key: str,
    msg: Map,
    payload: bytes,
    timeout: float,
    refused: list[Event],
) -> Put:
    """Wait until the storage answers with the map put, or says it did not take it (an Event
    in ``refused``); report what it holds otherwise."""
    digest = content_digest(msg)
    deadline = time.monotonic() + timeout
    while True:
        # A conflict is the store's only when it names a removed version (a running service's,
        # on the same key, may come before the store has stored what it took: its refusal is
        # _services_took's to say); the store's other refusals are said at once.
        said_by_store = [e for e in refused if _stores_own(e)]
        if said_by_store and said_by_store[0].code != EventCode.MAP_WRITE_FAILED:
            return Put(False, None, f"the store did not take {key}: {said_by_store[0].message}")
        held, in_memory = held_reply(session, key, min(timeout, 2.0), unless=payload)
        if held is payload or (isinstance(held, Map) and content_digest(held) == digest):
            if in_memory or said_by_store:
                said = f"put {key} (version {msg.version}): taken, but {_NOT_WRITTEN}"
                return Put(False, msg.version, said, new=True)
            said = f"put {key} (version {msg.version}, {len(payload)} bytes): stored"
            return Put(True, msg.version, said, new=True)
        assert not isinstance(held, bytes)
        if held is not None and held.version >= msg.version:
            return Put(False, held.version, _refused(key, msg.version, held.version))
        if time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    if held is None:
        return Put(
            False,
            None,
            f"no storage answered for {key} within {timeout:g} s: the map was put but nothing "
            "holds it (start `rlutf serve`, which hosts the store, or zenohd with a storage on "
            "the maps' keys)",
        )
    return Put(
        False,
        held.version,
        f"the storage still holds version {held.version} of {key} after {timeout:g} s; version "
        f"{msg.version} was not confirmed (a store busy with other map puts drops more with an "
        "Event map_dropped: `rlutf events`; put it again, or give it longer with --timeout)",
    )


def get_map(
    session: zenoh.Session, prefix: str, map_id: str, out: Path | None, timeout: float
) -> int:
    """Print (or write) a stored map."""
    if not valid_id(map_id):
        print(f"rlutf map get: invalid map id {map_id!r}", file=sys.stderr)
        return 2
    key = Keys(prefix).map(map_id)
    refused = ""
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        payload = reply.ok.payload.to_bytes()
        try:  # any client may answer on a map key: only a map is printed or written
            decode(Map, payload, max_bytes=len(payload))
        except SchemaError as err:
            refused = f"; an answer for {key} is no map ({str(err)[:200]}), skipped"
            continue
        if out is not None:
            out.write_bytes(payload)
            print(f"wrote {out}")
        else:
            sys.stdout.write(payload.decode() + "\n")
        return 0
    print(
        f"rlutf map get: no storage answered for {key} within {timeout:g} s{refused} (`rlutf "
        "map list` shows the stored maps)",
        file=sys.stderr,
    )
    return 1
