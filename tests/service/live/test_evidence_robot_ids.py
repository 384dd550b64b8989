"""Map evidence put on the bus by any client holds a bounded number of robot ids.

Found by a reviewer attacking a running ``rlutf serve`` from a Zenoh client: 20 puts on
``rlutf/service/evil/mapevidence`` of 100,000 made-up robot ids each (an empty grid of the map's
shape, 93 kB apiece compressed) were merged into the map's grid, which kept every id: the
service grew by 330 MB and its MapHealth said ``"robots": 2000003``; more puts, more memory,
without end. A grid now remembers at most :data:`rlutf.mapchange.ROBOT_IDS_MAX` ids. Real
Zenoh sessions on loopback.
"""

from __future__ import annotations

import json
import time

import numpy as np
import zenoh
import zstandard
from shapely.geometry import box

from rlutf import mapchange
from rlutf.map import Map as World
from rlutf.mapchange import ChangeGrid, Returns
from schemas import Map, encode
from service.keys import Keys
from service.live.healthfeed import HealthFeed
from service.live.sessions import free_port, session_config
from service.maphealth import Handed
from service.maps.book import MapBook

T0 = 1_700_000_000_000_000_000
IDS = 60_000  # per payload (the evidence's own bound is 100,000)


def _payload(shape: tuple[int, int], batch: int) -> bytes:
    head = {
        "maps": [
            {
                "map_id": "m1",
                "version": 1,
                "shape": list(shape),
                "cells": 0,
                "scans": 1,
                "oldest_ns": T0,
                "newest_ns": T0,
                "robots": [f"fake{batch}-{i:06d}" for i in range(IDS)],
            }
        ]
    }
    raw = json.dumps(head, separators=(",", ":")).encode() + b"\n"
    return bytes(zstandard.ZstdCompressor(level=1).compress(raw))


def _grid(feed: HealthFeed) -> ChangeGrid:
    with feed._lock:
        grid = feed.engine._maps["m1"].grid
    assert grid is not None
    return grid


def test_evidence_of_made_up_robot_ids_is_held_to_a_bound() -> None:
    world = World.from_shapely(box(0.0, 0.0, 10.0, 6.0))
    book = MapBook(10**8)
    book.offer(
        "m1",
        encode(Map.model_validate({"map_id": "m1", "version": 1, "geometry": world.to_geojson()})),
        T0,
    )
    loaded = book.get("m1")
    assert loaded is not None and loaded.world is not None
    feed = HealthFeed(Keys(), book, lambda key, data: None, lambda *record: None, time.time_ns)
    feed.share_as("i1", 64 << 20, lambda key: True)
    grid = ChangeGrid(loaded.world)
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), 8.0 / np.cos(angles))  # fmt: skip
    grid.add(ret, T0, "r1")
    feed.on_evidence([Handed("m1", 1, grid.snapshot())])  # this instance's own robot
    shape = (grid.nx, grid.ny)
    refused: list[str] = []
    feed.refused = lambda key, why: refused.append(why)  # type: ignore[method-assign]
    port = free_port()
    with zenoh.open(session_config("peer", listen=[f"tcp/127.0.0.1:{port}"])) as session:
        merging = feed.declare(session)
        attacker = zenoh.open(session_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
        try:
            for batch in range(3):  # 180,000 made-up ids in all
                attacker.put("rlutf/service/evil/mapevidence", _payload(shape, batch))
                time.sleep(0.3)
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                if _grid(feed).scans >= 4:
                    break
                time.sleep(0.1)
        finally:
            attacker.close()
            merging.undeclare()
    assert refused == []
    merged = _grid(feed)
    assert merged.scans == 4  # all three merged
    assert len(merged.robot_ids) == mapchange.ROBOT_IDS_MAX
    assert "r1" in merged.robot_ids  # the ones held before are kept
    answer = feed.engine.answer("m1")  # made anew (one of the last second may be answered)
    assert answer is not None and json.loads(answer)["robots"] == mapchange.ROBOT_IDS_MAX
