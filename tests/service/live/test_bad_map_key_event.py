"""A map put on a key whose id is not ``[A-Za-z0-9_-]{1,64}`` gets one Event ``invalid_key`` on
``{prefix}/events`` (WIRE.md, Keys), not also an ``invalid_map`` from the embedded store.

Real service (with its embedded store) and client session on loopback (the harness's bench).
"""

from __future__ import annotations

import json
import time

import pytest
from service_harness import JSON, Bench, Collector

pytestmark = pytest.mark.integration


def test_a_bad_map_id_gets_one_invalid_key(bench: Bench) -> None:
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", col)
    try:
        body = {"map_id": "bad.id", "version": 1, "geometry": bench.world.to_geojson()}
        bench.client.put("rlutf/maps/bad.id", json.dumps(body), encoding=JSON)
        assert col.wait_for(lambda: len(col.on("rlutf/events")) > 0, 10.0)
        time.sleep(1.5)  # anything else it says about the put
    finally:
        sub.undeclare()
    about = [e for e in col.on("rlutf/events") if e["key"] == "rlutf/maps/bad.id"]
    assert [e["code"] for e in about] == ["invalid_key"], about
