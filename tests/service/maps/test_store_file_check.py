"""The embedded store serves a map's file only while it holds what the store holds, says which
file changed under it and what to do, and a put of the map repairs it."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import zenoh
from service_harness import WORLD

from schemas import Map, encode
from service.keys import Keys
from service.live.sessions import session_config
from service.maps.files import FileMapStore
from service.maps.store import MapStorage

JSON = zenoh.Encoding.APPLICATION_JSON


def _payload(version: int) -> bytes:
    return encode(Map(map_id="m1", version=version, geometry=WORLD.to_geojson()))


def _other_walls(version: int) -> bytes:
    square = {"type": "Polygon", "coordinates": [[[0, 0], [5, 0], [5, 5], [0, 5], [0, 0]]]}
    return json.dumps({"map_id": "m1", "version": version, "geometry": square}).encode()


def _served(session: zenoh.Session) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get("rlutf/maps/*", timeout=1.0) if r.ok]


def _until(check: object, seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while not check() and time.monotonic() < deadline:  # type: ignore[operator]
        time.sleep(0.05)


@pytest.mark.integration
def test_a_file_changed_on_disk_is_said_not_served_and_a_put_repairs_it(tmp_path: Path) -> None:
    file = tmp_path / "m1.json"
    with zenoh.open(session_config("peer")) as session:
        said: list[str] = []
        storage = MapStorage(
            session,
            Keys(),
            FileMapStore(tmp_path),
            10_000_000,
            on_error=lambda k, m: said.append(m),
        )
        try:
            session.put("rlutf/maps/m1", _payload(1), encoding=JSON)
            _until(lambda: _served(session) == [_payload(1)])
            assert _served(session) == [_payload(1)] and said == []

            damaged = {
                "holds version 1 with other content": _other_walls(1),
                "holds no valid map": b'{"map_id": "m1", nope',
                "holds no valid map (malformed": _payload(1)[:100],
                "holds no valid map (malformed JSON": b"",
            }
            for what, content in damaged.items():
                time.sleep(1.1)  # the store's read of the last one is answered again for 1 s
                said.clear()
                file.write_bytes(content)
                assert _served(session) == [] and _served(session) == []
                assert len(said) == 1, said  # once per change, not once per get
                assert f"file {file} {what}" in said[0] and "rlutf map put" in said[0]
            file.unlink()
            said.clear()
            assert _served(session) == [] and _served(session) == []
            assert len(said) == 1 and f"file {file} is gone" in said[0]

            # the operator puts the map again, the very version held: its file is written again
            session.put("rlutf/maps/m1", _payload(1), encoding=JSON)
            _until(lambda: _served(session) == [_payload(1)])
            assert _served(session) == [_payload(1)] and file.read_bytes() == _payload(1)
            said.clear()
            # a put of a newer version is stored and served as before, with no word
            session.put("rlutf/maps/m1", _payload(2), encoding=JSON)
            _until(lambda: _served(session) == [_payload(2)])
            assert _served(session) == [_payload(2)] and said == []
        finally:
            storage.close()


@pytest.mark.integration
def test_an_invalid_file_at_start_is_said_with_its_path(tmp_path: Path) -> None:
    (tmp_path / "m1.json").write_bytes(b'{"map_id": "m1", nope')
    with zenoh.open(session_config("peer")) as session:
        said: list[str] = []
        storage = MapStorage(
            session,
            Keys(),
            FileMapStore(tmp_path),
            10_000_000,
            on_error=lambda k, m: said.append(m),
        )
        try:
            assert len(said) == 1 and str(tmp_path / "m1.json") in said[0]
            assert "rlutf map put" in said[0] and _served(session) == []
        finally:
            storage.close()


@pytest.mark.integration
def test_map_put_next_repairs_or_supersedes_a_map_held_but_not_served(tmp_path: Path) -> None:
    """`rlutf map put FILE` (version next) learnt the version from the map served: none, so it
    put version 1, which the store (holding version 1) refused with no answer: exit 1, 'no
    storage answered'. It now asks the store what it holds."""
    from service.maps.client import put_payload

    file = tmp_path / "m1.json"
    with zenoh.open(session_config("peer")) as session:
        storage = MapStorage(session, Keys(), FileMapStore(tmp_path), 10_000_000)
        try:
            session.put("rlutf/maps/m1", _payload(1), encoding=JSON)
            _until(lambda: _served(session) == [_payload(1)])
            file.unlink()
            time.sleep(1.1)  # the store's last read is answered again for 1 s
            put = put_payload(session, "rlutf", _payload(0), timeout=3.0)  # the same walls
            assert put.stored and put.version == 1, put
            assert file.read_bytes() == _payload(1)
            file.write_bytes(b"")
            time.sleep(1.1)
            put = put_payload(session, "rlutf", _other_walls(7), timeout=3.0)
            assert put.stored and put.version == 2, put
            assert json.loads(file.read_bytes())["version"] == 2
        finally:
            storage.close()
