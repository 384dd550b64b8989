"""The workers' map health evidence is merged and reported on the feed's own thread.

It comes with their outputs, on the thread that publishes every robot's pose; a report walks
the map's grid and builds a polygon per change (a second and more for a warehouse with
thousands of pallets the map lacks), and was made right there, holding back the poses that
came after it, once a second."""

from __future__ import annotations

import contextlib
import queue
import threading
import time

import numpy as np
import pytest
import zenoh
from shapely.geometry import box

from rlutf.map import Map as World
from rlutf.mapchange import ChangeGrid, Returns
from schemas import Map, encode
from service.keys import Keys
from service.live.healthfeed import HealthFeed
from service.live.sessions import free_port, session_config
from service.maphealth import Handed
from service.maps.book import MapBook

T0 = 1_700_000_000_000_000_000


def test_a_report_is_made_on_the_feeds_thread_not_on_the_poses_thread() -> None:
    world = World.from_shapely(box(0.0, 0.0, 10.0, 6.0))
    payload = encode(
        Map.model_validate({"map_id": "m1", "version": 1, "geometry": world.to_geojson()})
    )
    book = MapBook(10**8)
    book.offer("m1", payload, T0)
    reported = threading.Event()
    puts: list[tuple[str, str]] = []

    def publish(key: str, data: bytes) -> None:
        puts.append((key, threading.current_thread().name))
        if key == "rlutf/maphealth/m1":
            reported.set()

    feed = HealthFeed(Keys(), book, publish, lambda *record: None, time.time_ns)
    feed.share_as("i1", 64 << 20, lambda key: True)
    # an object at x = 5 the map lacks, seen from (2, 3) over 30 s
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), 8.0 / np.cos(angles))  # fmt: skip
    loaded = book.get("m1")
    assert loaded is not None and loaded.world is not None
    grid = ChangeGrid(loaded.world)
    for k in range(30):
        grid.add(ret, T0 + k * 1_000_000_000, "r1")
    config = session_config("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    with zenoh.open(config) as session:
        merging = feed.declare(session)
        feed.on_evidence([Handed("m1", 1, grid.snapshot())])  # as the poses' thread does
        assert reported.wait(10.0)
        merging.undeclare()
    health = [thread for key, thread in puts if key == "rlutf/maphealth/m1"]
    assert health and threading.current_thread().name not in health, puts
    assert feed.engine.answer("m1") is not None


def test_own_evidence_never_waits_behind_a_flood_of_other_instances_payloads() -> None:
    """The thread that hands this instance's evidence on publishes the poses: a queue full of
    other instances' payloads (a flood on ``{prefix}/service/*/mapevidence``) must not hold it
    up. Before, it waited for room in that queue; now it is kept aside and merged first."""
    from service.live import healthfeed

    world = World.from_shapely(box(0.0, 0.0, 10.0, 6.0))
    payload = encode(
        Map.model_validate({"map_id": "m1", "version": 1, "geometry": world.to_geojson()})
    )
    book = MapBook(10**8)
    book.offer("m1", payload, T0)
    feed = HealthFeed(Keys(), book, lambda key, data: None, lambda *record: None, time.time_ns)
    feed.share_as("i1", 64 << 20, lambda key: True)
    release = threading.Event()
    shared = feed.on_shared

    def slow(data: bytes, report: bool = True) -> str | None:  # each payload takes long
        release.wait(10.0)
        return shared(data, report)

    feed.on_shared = slow  # type: ignore[method-assign, assignment]
    loaded = book.get("m1")
    assert loaded is not None and loaded.world is not None
    grid = ChangeGrid(loaded.world)
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), 8.0 / np.cos(angles))  # fmt: skip
    grid.add(ret, T0, "r1")
    config = session_config("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    with zenoh.open(config) as session:
        merging = feed.declare(session)
        with contextlib.suppress(queue.Full):  # one being merged, then the queue full
            for _ in range(healthfeed.WAITING + 2):
                merging._waiting.put_nowait(("rlutf/service/x/mapevidence", b"{}"))
        assert merging._waiting.full()
        started = time.monotonic()
        for _ in range(20):
            feed.on_evidence([Handed("m1", 1, grid.snapshot())])
        assert time.monotonic() - started < 1.0  # it waited 10 s per call before
        release.set()
        deadline = time.monotonic() + 10.0
        while feed.engine.answer("m1") is None and time.monotonic() < deadline:
            time.sleep(0.05)
        merging.undeclare()
    assert feed.engine.answer("m1") is not None  # own evidence merged all the same


def test_other_instances_payloads_wait_within_a_bound_in_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each payload may be up to max_map_bytes (64 MiB), and 32 could wait: 2 GiB held by a
    flood. The waiting payloads are bounded in bytes too; one is always taken when none waits."""
    from service.live import healthfeed

    monkeypatch.setattr(healthfeed, "WAITING_BYTES", 1500)
    book = MapBook(10**8)
    feed = HealthFeed(Keys(), book, lambda key, data: None, lambda *record: None, time.time_ns)
    feed.share_as("i1", 64 << 20, lambda key: True)
    refused: list[str] = []
    feed.refused = lambda key, why: refused.append(why)  # type: ignore[method-assign]
    release = threading.Event()
    shared = feed.on_shared

    def slow(data: bytes, report: bool = True) -> str | None:
        release.wait(10.0)
        return shared(data, report)

    feed.on_shared = slow  # type: ignore[method-assign, assignment]
    config = session_config("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    with zenoh.open(config) as session:
        merging = feed.declare(session)
        for i in range(4):  # 1 kB each: one merged (held up), one waits, the others do not fit
            session.put("rlutf/service/x/mapevidence", bytes([i]) * 1000)
            time.sleep(0.2)
        deadline = time.monotonic() + 5.0
        while len(refused) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        release.set()
        merging.undeclare()
    dropped = [why for why in refused if "dropped" in why]  # the others: merged, not evidence
    assert dropped == ["map evidence dropped: 1 payloads (0.0 MB) already wait to be merged"] * 2


def test_a_get_of_one_maps_health_makes_no_report_of_the_others() -> None:
    """A report walks the map's grid (a second and more on a large map): a get of one map's
    MapHealth made one for every map with evidence, on Zenoh's callback thread."""
    book = MapBook(10**8)
    grids = {}
    for map_id in ("m1", "m2"):
        world = World.from_shapely(box(0.0, 0.0, 10.0, 6.0))
        payload = encode(
            Map.model_validate({"map_id": map_id, "version": 1, "geometry": world.to_geojson()})
        )
        book.offer(map_id, payload, T0)
        loaded = book.get(map_id)
        assert loaded is not None and loaded.world is not None
        grids[map_id] = ChangeGrid(loaded.world)
    feed = HealthFeed(Keys(), book, lambda key, data: None, lambda *record: None, time.time_ns)
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), 8.0 / np.cos(angles))  # fmt: skip
    for map_id, grid in grids.items():
        grid.add(ret, T0, "r1")
        feed.on_evidence([Handed(map_id, 1, grid.snapshot())])
    made: list[str] = []
    report = feed.engine._report

    def counted(map_id: str, state: object) -> bytes:
        made.append(map_id)
        return report(map_id, state)  # type: ignore[arg-type]

    feed.engine._report = counted  # type: ignore[method-assign, assignment]
    for state in feed.engine._maps.values():
        state.report = None  # nothing reported yet
    config = session_config("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    with zenoh.open(config) as session:
        queryable = session.declare_queryable("rlutf/maphealth/*", feed.on_query)
        replies = [r.ok.key_expr for r in session.get("rlutf/maphealth/m1", timeout=2.0) if r.ok]
        queryable.undeclare()
    assert [str(k) for k in replies] == ["rlutf/maphealth/m1"]
    assert made == ["m1"], made


def test_with_maps_checked_apart_the_validating_process_builds_the_map_at_its_first_evidence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A main process with worker processes holds no map (the book's map is ``None``): map
    health's walls came from decoding and validating the payload here, which held the lock for
    up to 0.8 s for a 10 MB map. The validating process builds it now, at the version's first
    evidence only; a build that fails drops that map's evidence and is tried again later."""
    from service.live import healthfeed

    world = World.from_shapely(box(0.0, 0.0, 10.0, 6.0))
    payload = encode(
        Map.model_validate({"map_id": "m1", "version": 1, "geometry": world.to_geojson()})
    )
    book = MapBook(10**8, isolated=True)
    book.checker.inline_bytes = 0  # the map is small: taken as one over INLINE_BYTES
    now = [T0]
    feed = HealthFeed(Keys(), book, lambda key, data: None, lambda *record: None, lambda: now[0])
    try:
        book.offer("m1", payload, T0)
        loaded = book.get("m1")
        assert loaded is not None and loaded.world is None
        calls = book.checker.process.started  # one process so far, which checked the map
        grid = ChangeGrid(world)
        angles = np.linspace(-0.2, 0.2, 36)
        ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                      3.0 / np.cos(angles), 8.0 / np.cos(angles))  # fmt: skip
        for k in range(30):
            grid.add(ret, T0 + k * 1_000_000_000, "r1")
        evidence = [Handed("m1", 1, grid.snapshot())]

        # the validating process fails (too slow: stopped): no map, the evidence dropped ...
        book.checker.process.timeout_s = 0.0
        feed.on_evidence(evidence)  # merged on this thread: no feed thread declared
        assert feed.engine.version("m1") is None and feed.engine.answer("m1") is None
        book.checker.process.timeout_s = 30.0
        feed.on_evidence(evidence)  # ... and not asked again at once
        assert feed.engine.version("m1") is None and book.checker.process.pid is None
        now[0] += int(healthfeed.RETRY_S * 1e9)  # asked again later: built there, sent back
        building = book.checker.process.started
        feed.on_evidence(evidence)
        assert book.checker.process.started == building + 1 > calls
        held = feed.engine._maps["m1"].world
        assert held is not world and held.geometry.equals_exact(world.geometry, 0.0)
        assert np.array_equal(held.segments, world.segments)
        assert book.get("m1").world is None  # type: ignore[union-attr]  # kept by the feed only
        answer = feed.engine.answer("m1")
        assert answer is not None and b'"added"' in answer

        # later evidence of the version asks for no map
        monkeypatch.setattr(book, "world_of", None)  # calling it would raise
        feed.on_evidence(evidence)
        assert feed.engine._maps["m1"].world is held
    finally:
        book.checker.close()
