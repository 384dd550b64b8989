"""What a live service puts under ``rlutf/**`` is labelled as what it is: JSON as
``application/json`` (WIRE.md), and the map health evidence the instances share, a zstd frame,
as bytes (it was labelled ``application/json``, so a tool subscribed to ``rlutf/**`` that decodes
by encoding failed on it).

Real service and client session on loopback (the harness's bench).
"""

from __future__ import annotations

import json
import threading
import time

import pytest
import zenoh
from service_harness import Bench, wait_until

pytestmark = pytest.mark.integration


def test_every_put_is_labelled_as_what_it_holds(bench: Bench) -> None:
    seen: dict[str, set[str]] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        kind = "mapevidence" if key.endswith("/mapevidence") else key.rsplit("/", 1)[-1]
        encoding = str(sample.encoding)
        if encoding.startswith("application/json"):
            try:
                json.loads(sample.payload.to_bytes())
            except ValueError:
                encoding += " (not JSON)"  # labelled JSON, but is not
        with lock:
            seen.setdefault(kind, set()).add(encoding)

    sub = bench.client.declare_subscriber("rlutf/**", on_sample)
    try:
        bench.put_map()
        assert wait_until(lambda: "m1" in bench.service.maps_held())
        robot = bench.robot("r1", 5)
        robot.initial_pose("m1")
        time.sleep(0.2)
        end = time.monotonic() + 15
        while time.monotonic() < end and "mapevidence" not in seen:
            robot.advance()
            time.sleep(0.05)
    finally:
        sub.undeclare()
    assert seen.get("mapevidence") == {"application/octet-stream"}, seen
    assert seen.get("pose") == {"application/json"}, seen
