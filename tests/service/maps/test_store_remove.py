"""A map removed on purpose (a delete on its key) leaves the embedded store for good."""

from __future__ import annotations

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


def test_the_file_store_forgets_a_removed_map(tmp_path: Path) -> None:
    store = FileMapStore(tmp_path)
    store.put("m1", _payload(1))
    store.delete("m1")
    store.delete("m1")  # twice: nothing to do
    assert store.ids() == [] and store.get("m1") is None
    assert list(tmp_path.iterdir()) == []


def _served(session: zenoh.Session) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get("rlutf/maps/*", timeout=1.0) if r.ok]


@pytest.mark.integration
def test_a_delete_on_the_key_removes_the_map_and_its_version(tmp_path: Path) -> None:
    with zenoh.open(session_config("peer")) as session:
        conflicts: list[str] = []
        storage = MapStorage(
            session,
            Keys(),
            FileMapStore(tmp_path),
            10_000_000,
            on_conflict=lambda key, msg: conflicts.append(msg),
        )
        try:
            session.put("rlutf/maps/m1", _payload(3), encoding=JSON)
            deadline = time.monotonic() + 5
            while not _served(session) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _served(session) == [_payload(3)]

            session.delete("rlutf/maps/m1")
            while _served(session) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _served(session) == []
            assert not (tmp_path / "m1.json").exists()
            # the removal kept version 3 (running services keep their copy): version 1 is an
            # older version, refused and said; version 3 as it was is put back; then 4 is new
            session.put("rlutf/maps/m1", _payload(1), encoding=JSON)
            while not conflicts and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _served(session) == [] and "not newer than version 3" in conflicts[0]
            assert storage.held("m1") is not None and storage.held("m1")[0] == 3
            session.put("rlutf/maps/m1", _payload(3), encoding=JSON)
            while not _served(session) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _served(session) == [_payload(3)]
            assert not (tmp_path / ".m1.removed").exists()
        finally:
            storage.close()
    # and a store opened on the folder again serves what is left
    assert FileMapStore(tmp_path).ids() == ["m1"]


def test_the_version_removed_is_kept_across_restarts(tmp_path: Path) -> None:
    store = FileMapStore(tmp_path)
    store.put("m1", _payload(3))
    store.delete("m1", (3, "digest"))
    assert store.ids() == [] and FileMapStore(tmp_path).removed() == {"m1": (3, "digest")}
    store.unmark("m1")
    assert FileMapStore(tmp_path).removed() == {}
    assert list(tmp_path.iterdir()) == []
