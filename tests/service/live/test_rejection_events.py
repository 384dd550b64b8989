"""A robot's malformed inputs: every one rejected and counted, Events at most one per interval.

Anyone can write on a robot's keys. A flood of malformed scans used to cost an Event and a
record of the service's log per message; now one per robot and ``event_interval_s``, the next
counting those held back, while an operator's request (an InitialPose, a Relocalize) is still
answered each time (`rlutf initialpose` waits for its Event).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from service_harness import Collector, running_bench

from service.live.admission import REJECTIONS_KEPT, Gate

SCAN_BODY = (
    b'"angle_min": 0, "angle_increment": 0.1, "range_min": 0.1, "range_max": 9, "ranges": [1]'
)


def test_the_gate_holds_back_a_robot_s_rejections_within_the_interval() -> None:
    gate = Gate(lambda: 0, 10**9, 10, event_interval_ns=1_000)
    assert gate.rejection("r1", "invalid_message", 0) == 0
    assert [gate.rejection("r1", "invalid_message", t) for t in (1, 500, 999)] == [None] * 3
    assert gate.rejection("r2", "invalid_message", 2) == 0, "another robot is its own"
    assert gate.rejection("r1", "stamp_rejected", 3) == 0, "another code is its own"
    assert gate.rejection("r1", "invalid_message", 1_000) == 3, "the held back, counted"
    assert gate.rejection("r1", "invalid_message", 2_000) == 0


def test_the_gate_s_memory_of_robots_is_bounded() -> None:
    gate = Gate(lambda: 0, 10**9, 10, event_interval_ns=10**9)
    for k in range(REJECTIONS_KEPT + 10):
        assert gate.rejection(f"r{k}", "invalid_message", k) == 0
    assert len(gate._rejections) <= REJECTIONS_KEPT


@pytest.mark.integration
def test_a_flood_of_malformed_scans_costs_one_event_per_interval(tmp_path: Path) -> None:
    with running_bench(tmp_path, event_interval_s=30.0) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/robots/*/events", col)
        time.sleep(0.5)
        for _ in range(100):
            b.client.put("rlutf/robots/r1/scan", b'{"stamp_ns": 1}')
        b.client.put("rlutf/robots/r2/odom", b"not json")
        for _ in range(3):  # an operator's request is answered each time
            b.client.put("rlutf/robots/r1/initialpose", b'{"stamp_ns": 1}')

        def codes(robot: str) -> list[tuple[object, object]]:
            return [(e["code"], e["key"]) for e in col.on(f"rlutf/robots/{robot}/events")]

        scan_key, pose_key = "rlutf/robots/r1/scan", "rlutf/robots/r1/initialpose"
        expected = [("invalid_message", scan_key)] + [("invalid_message", pose_key)] * 3
        assert col.wait_for(lambda: sorted(codes("r1")) == sorted(expected)), codes("r1")
        assert col.wait_for(lambda: codes("r2") == [("invalid_message", "rlutf/robots/r2/odom")])
        assert col.wait_for(lambda: b.service.stats.rejected >= 104)
        time.sleep(0.5)
        assert sorted(codes("r1")) == sorted(expected), "a flood must cost one Event an interval"
        sub.undeclare()


@pytest.mark.integration
def test_the_next_event_counts_the_rejections_held_back(tmp_path: Path) -> None:
    with running_bench(tmp_path, event_interval_s=0.5) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/robots/r1/events", col)
        time.sleep(0.5)
        for _ in range(20):
            b.client.put("rlutf/robots/r1/scan", b"[]")
        time.sleep(0.8)
        b.client.put("rlutf/robots/r1/scan", b"[]")
        events = lambda: col.on("rlutf/robots/r1/events")  # noqa: E731
        assert col.wait_for(lambda: len(events()) == 2), events()
        assert "(19 more like it since the last such Event)" in str(events()[1]["message"])
        sub.undeclare()


@pytest.mark.integration
def test_a_robot_whose_clock_is_ahead_costs_one_stamp_event_per_interval(tmp_path: Path) -> None:
    """A robot whose clock is an hour ahead stamps every scan and odometry so: each is rejected
    and counted, but it used to cost an Event per message (up to ten a second, each logged and
    recorded) where every other rejection costs one per robot and ``event_interval_s``; and
    another robot's clock then went unsaid, the ten Events a second all taken."""
    with running_bench(tmp_path, event_interval_s=30.0) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/robots/*/events", col)
        time.sleep(0.5)
        ahead = time.time_ns() + 3_600 * 10**9
        for k in range(30):
            odom = b'{"stamp_ns": %d, "x": 0, "y": 0, "theta": 0}' % (ahead + k)
            b.client.put("rlutf/robots/r1/odom", odom)
            scan = b'{"stamp_ns": %d, %s}' % (ahead + k, SCAN_BODY)
            b.client.put("rlutf/robots/r1/scan", scan)
        b.client.put(
            "rlutf/robots/r2/odom", b'{"stamp_ns": %d, "x": 0, "y": 0, "theta": 0}' % ahead
        )

        def codes(robot: str) -> list[object]:
            return [e["code"] for e in col.on(f"rlutf/robots/{robot}/events")]

        assert col.wait_for(lambda: b.service.gate.stamps_rejected >= 61)
        assert col.wait_for(lambda: codes("r2") == ["stamp_rejected"]), "another robot is its own"
        time.sleep(0.5)
        assert codes("r1") == ["stamp_rejected"], codes("r1")
        sub.undeclare()
