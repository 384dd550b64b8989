"""A map put that Zenoh did not deliver to a service without a store (a router drops a message
of many fragments it cannot send on within 50 ms: a 10 MB map put to a busy host's other
process, in `python -m bench.bigmap --processes 2`) still reaches it: it asks the store for
the versions of the maps it holds every ``LOOK_S`` seconds and fetches those it is behind on.
A real service with its file-backed store and a storeless one, on loopback."""

from __future__ import annotations

from pathlib import Path

import pytest
import zenoh
from service_harness import WORLD, Collector, running_bench, storeless_service, wait_until
from shapely import affinity

from rlutf.map import Map as World
from schemas import Map, StoredVersion, encode
from service.live import mapfeed
from service.maps.confirmation import StoreWatch

JSON = zenoh.Encoding.APPLICATION_JSON
MOVED = World.from_shapely(affinity.translate(WORLD.geometry, 0.01, 0.0))


def _version(service: object, map_id: str = "m1") -> int | None:
    loaded = service.maps.get(map_id)  # type: ignore[attr-defined]
    return None if loaded is None else int(loaded.version)


def _missed_puts(
    tmp_path: Path, look_s: float, monkeypatch: pytest.MonkeyPatch
) -> list[tuple[int, int]]:
    """Version 1 of m1 put on the bus; then version 2 of m1 and version 1 of a new map m2 put on
    the store's own session and delivered there only (as by a router that dropped them on their
    way to the other process): the versions of m1 and m2 (0: none) a storeless service held
    then, at once and 5 s after the store's process loaded them, with ``look_s`` seconds between
    its looks at the store. What it loaded is the very put, and said as a load."""
    monkeypatch.setattr(mapfeed, "LOOK_S", look_s)
    with running_bench(tmp_path) as bench:
        other = storeless_service(bench, event_interval_s=0.0)
        try:
            col = Collector()
            sub = bench.client.declare_subscriber("rlutf/events", col)
            bench.put_map("m1", version=1)
            assert wait_until(lambda: _version(other) == 1)
            payloads = {
                "m1": encode(Map(map_id="m1", version=2, geometry=MOVED.to_geojson())),
                "m2": encode(Map(map_id="m2", version=1, geometry=WORLD.to_geojson())),
            }
            session = bench.service._session
            assert session is not None
            for map_id, payload in payloads.items():
                session.put(
                    f"rlutf/maps/{map_id}",
                    payload,
                    encoding=JSON,
                    allowed_destination=zenoh.Locality.SESSION_LOCAL,
                )
            assert wait_until(
                lambda: (_version(bench.service), _version(bench.service, "m2")) == (2, 1)
            )

            def both() -> tuple[int, int]:
                return _version(other) or 0, _version(other, "m2") or 0

            held = [both()]
            wait_until(lambda: both() == (2, 1), 5.0)
            held.append(both())
            for map_id, version in (("m1", 2), ("m2", 1)):
                loaded = other.maps.get(map_id)
                if loaded is not None and loaded.version == version:
                    assert loaded.payload == payloads[map_id]
                    said = f"map {map_id} version {version} loaded"  # by both processes
                    assert col.wait_for(
                        lambda s=said: [e["message"] for e in col.on("rlutf/events")].count(s) == 2
                    ), col.on("rlutf/events")
            sub.undeclare()
        finally:
            other.close()
    return held


def test_puts_the_bus_did_not_deliver_are_not_seen_without_a_look(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert _missed_puts(tmp_path, 3600.0, monkeypatch) == [(1, 0), (1, 0)]


def test_puts_the_bus_did_not_deliver_are_fetched_from_the_store(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # m1, held here in version 1, and m2, which this process never held
    assert _missed_puts(tmp_path, 0.5, monkeypatch)[-1] == (2, 1)


def test_a_process_with_the_store_does_not_look(tmp_path: Path) -> None:
    with running_bench(tmp_path) as bench:
        assert bench.service.mapfeed._next_look is None
        other = storeless_service(bench)
        try:
            assert other.mapfeed._next_look is not None
        finally:
            other.close()


def test_what_a_look_at_the_store_fetches() -> None:
    def answer(map_id: str, version: int | None, **kw: object) -> StoredVersion:
        digest = None if version is None else "ab" * 32
        return StoredVersion(map_id=map_id, version=version, digest=digest, **kw)  # type: ignore[arg-type]

    watch = StoreWatch()
    stored = {"old": answer("old", 3), "gone": answer("gone", 2, removed=True)}
    # the first look notes what the store held before: fetched on demand, as at a start
    assert watch.behind({}, stored) == []
    stored |= {
        "new": answer("new", 1),  # put since: fetched
        "busy": answer("busy", 1, pending=1),  # still being stored: looked at again
        "none": answer("none", None),
    }
    assert watch.behind({"old": (3, "ab" * 32)}, stored) == ["new"]
    assert watch.behind({}, stored) == ["new"]  # not fetched yet: again
    stored["busy"] = answer("busy", 1)
    stored["old"] = answer("old", 4)
    held = {"old": (3, "ab" * 32), "new": (1, "ab" * 32)}
    assert watch.behind(held, stored) == ["busy", "old"]
    assert watch.behind({"old": (5, "cd" * 32)}, stored) == ["busy"]  # a newer one here: kept
