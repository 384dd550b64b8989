"""ROS 2 inputs on a namespace that is no robot id: one instance reports, one Event an interval.

Every service process's front door reads every rmw_zenoh key, so a sample on `/bad ns!/scan`
reached each of them, and each put an Event ``invalid_key`` for it with no rate limit: 200 such
samples on `rlutf serve` (two processes) were 400 Events, where the same flood on the JSON keys
(made-up robot ids) is one Event a second from the one instance that owns the key.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Iterator
from types import SimpleNamespace

import pytest
import zenoh

from service.config import Settings
from service.keys import Keys
from service.live.intake import Intake
from service.live.keywatch import KeyWatch
from service.live.stats import Stats

INSTANCES = ("p0", "p1")
GRID_KEY = "0/map/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"


def _owner(key: str) -> str:
    return INSTANCES[zlib.crc32(key.encode()) % len(INSTANCES)]


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as s:
        yield s


def test_a_flood_on_namespaces_that_are_no_robot_id_costs_one_event_an_interval(
    session: zenoh.Session,
) -> None:
    settings = Settings(event_interval_s=30.0)
    keys = Keys()
    events: list[tuple[str, str, str, str]] = []
    intakes, watches, stats = [], [], []
    for me in INSTANCES:

        def report(level: str, code: str, key: str, message: str, at: int, me: str = me) -> None:
            events.append((me, code, key, message))

        def owns_key(key: str, me: str = me) -> bool:
            return _owner(key) == me

        watch = KeyWatch(keys, report, time.time_ns, settings, owns_key)
        st = Stats(me)
        watch.start(session, st)
        svc = SimpleNamespace(
            settings=settings,
            keys=keys,
            stats=st,
            ownership=SimpleNamespace(ready=True, owns=lambda robot: True),
            membership=SimpleNamespace(owns_key=owns_key),
            keywatch=watch,
            clock=time.time_ns,
            _global_event=lambda level, code, about, message, now=None, me=me: events.append(
                (me, code, about, message)
            ),
        )
        intakes.append(Intake(svc))  # type: ignore[arg-type]
        watches.append(watch)
        stats.append(st)
    try:
        hash_ = "TypeHashNotSupported"
        for i in range(200):  # each front door reads every sample
            key = f"0/bad.ns{i}/scan/sensor_msgs::msg::dds_::LaserScan_/{hash_}"
            for intake in intakes:
                intake.reject(None, key, f"namespace '/bad.ns{i}' is not a robot id", 10**9 + i)
        for intake in intakes:
            intake.reject(None, GRID_KEY, "map not imported: no map id", 2 * 10**9)
        deadline = time.monotonic() + 2.0
        while len(events) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.2)
    finally:
        for watch in watches:
            watch.close()
    scans = [e for e in events if e[2] != GRID_KEY]
    assert 1 <= len(scans) <= len(INSTANCES), len(scans)
    assert {code for _, code, _, _ in events} == {"invalid_key"}
    for me, _, key, _ in events:
        assert _owner(key) == me, "only the instance that owns the key reports it"
    assert sum(s.rejected for s in stats) == 201, "each counted once, by the instance reporting"
    grid = [m for _, _, k, m in events if k == GRID_KEY]
    assert grid == ["map not imported: no map id"], "a flood on scan keys hides no other topic's"
