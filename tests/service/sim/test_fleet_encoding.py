"""The simulated JSON robots label what they put ``application/json``, as WIRE.md says every
payload is (a dashboard that decodes by the sample's encoding read them as raw bytes before).

Real Zenoh sessions on loopback: a router with a subscriber, the fleet's client sessions.
"""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from service.live.sessions import client_config, free_port, session_config
from service.sim.fleet import SimFleet
from service.sim.plan import FleetSpec, Schedule, plan_fleet
from service.sim.wire import JsonWire

pytestmark = pytest.mark.integration


def test_json_robots_put_application_json() -> None:
    spec = FleetSpec(
        robots=2,
        poses=6,
        beams=60,
        seed=3,
        map_id="m1",
        relocalize=Schedule(every=1, robots=(0,)),
        bad_input=Schedule(every=1, robots=(1,)),
    )
    plan = plan_fleet(spec)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    seen: dict[str, set[str]] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        leaf = str(sample.key_expr).rsplit("/", 1)[-1]
        with lock:
            seen.setdefault(leaf, set()).add(str(sample.encoding))

    with zenoh.open(session_config("router", listen=[endpoint])) as router:
        sub = router.declare_subscriber("rlutf/robots/*/*", on_sample)
        fleet = SimFleet(plan, JsonWire(plan), lambda: zenoh.open(client_config(endpoint)), 1)
        try:
            time.sleep(0.5)
            fleet.start(time.time_ns())
            for step in (1, 2):
                assert fleet.extras(step, time.time_ns()) > 0
                for robot in range(2):
                    fleet.send(robot, step, time.time_ns())
            end = time.monotonic() + 5
            want = {"odom", "scan", "initialpose", "relocalize"}
            while time.monotonic() < end and not want <= set(seen):
                time.sleep(0.05)
        finally:
            fleet.close()
            sub.undeclare()
    assert want <= set(seen), seen
    assert all(encs == {"application/json"} for encs in seen.values()), seen
