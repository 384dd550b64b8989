"""Every InitialPose or Relocalize naming a map no storage holds gets ``map_not_found``
(WIRE.md, Relocalize), also when several robots name the same missing map at once.

Real service and client sessions on loopback (the harness's bench).
"""

from __future__ import annotations

import time

import pytest
from service_harness import JSON, Bench, Collector

from schemas import InitialPose, Relocalize, encode

pytestmark = pytest.mark.integration


def test_each_request_on_one_missing_map_is_answered(bench: Bench) -> None:
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/*/events", col)
    try:
        now = time.time_ns()
        for robot in ("p1", "p2"):
            pose = InitialPose(stamp_ns=now, map_id="nowhere", x=1.0, y=1.0, theta=0.0)
            bench.client.put(f"rlutf/robots/{robot}/initialpose", encode(pose), encoding=JSON)
        again = Relocalize(stamp_ns=now, map_id="nowhere")
        bench.client.put("rlutf/robots/p3/relocalize", encode(again), encoding=JSON)
        robots = ("p1", "p2", "p3")

        def answered() -> list[str]:
            return [
                r
                for r in robots
                if any(e["code"] == "map_not_found" for e in col.on(f"rlutf/robots/{r}/events"))
            ]

        assert col.wait_for(lambda: len(answered()) == 3, 10.0), answered()
        for robot in robots:
            event = next(
                e for e in col.on(f"rlutf/robots/{robot}/events") if e["code"] == "map_not_found"
            )
            assert "nowhere" in event["message"] and event["key"] == "rlutf/maps/nowhere"
    finally:
        sub.undeclare()
