"""Client tools over Zenoh for maps: put a map file into the store, get a stored map."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import zenoh

from schemas import Map, SchemaError, decode, encode, valid_id
from service.keys import Keys
from service.maps.book import MapRejected, load_map

JSON = zenoh.Encoding.APPLICATION_JSON


def map_message_from_file(path: Path, map_id: str | None, version: int | None) -> bytes:
    """A Map payload from a file holding a Map message or a bare GeoJSON geometry.

    Raises:
        ValueError: unreadable file, bad JSON, invalid id or invalid map (message says why).
    """
    try:
        data: Any = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise ValueError(f"cannot read {path}: {err.strerror}") from err
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: malformed JSON: {err}") from err
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    if data.get("type") in ("Polygon", "MultiPolygon"):
        data = {"geometry": data}
    if data.get("type") == "Feature":
        data = {"geometry": data.get("geometry")}
    mid = map_id or data.get("map_id") or path.stem.split(".")[0]
    if not valid_id(str(mid)):
        raise ValueError(f"map id {mid!r} does not match [A-Za-z0-9_-]{{1,64}}; use --id")
    data["map_id"] = mid
    data["version"] = version if version is not None else data.get("version", 1)
    data.setdefault("frame_id", "map")
    try:
        msg = decode(Map, json.dumps(data))
        payload = encode(msg)
        load_map(payload, expected_id=str(mid), max_bytes=10**9)
    except (SchemaError, MapRejected) as err:
        raise ValueError(f"{path}: invalid map: {err}") from err
    return payload


def put_map(
    session: zenoh.Session, prefix: str, path: Path, map_id: str | None, version: int | None
) -> int:
    """Put a map file into whatever storage holds ``{prefix}/maps/**``."""
    try:
        payload = map_message_from_file(path, map_id, version)
    except ValueError as err:
        print(f"rlutf map put: {err}", file=sys.stderr)
        return 1
    msg = decode(Map, payload)
    key = Keys(prefix).map(msg.map_id)
    session.put(key, payload, encoding=JSON)
    print(f"put {key} (version {msg.version}, {len(payload)} bytes)")
    return 0


def get_map(
    session: zenoh.Session, prefix: str, map_id: str, out: Path | None, timeout: float
) -> int:
    """Print (or write) a stored map."""
    if not valid_id(map_id):
        print(f"rlutf map get: invalid map id {map_id!r}", file=sys.stderr)
        return 2
    key = Keys(prefix).map(map_id)
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        payload = reply.ok.payload.to_bytes()
        if out is not None:
            out.write_bytes(payload)
            print(f"wrote {out}")
        else:
            sys.stdout.write(payload.decode() + "\n")
        return 0
    print(
        f"rlutf map get: no storage answered for {key} within {timeout:g} s (`rlutf map list` "
        "shows the stored maps)",
        file=sys.stderr,
    )
    return 1
