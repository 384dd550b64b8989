"""Bounded work per input (service.guard): limits beyond the schema, capped ranges, rollback.

Every input over a limit gives an Event ``invalid_message`` naming the field and the value and
changes nothing: the robot's later poses are those of an engine that never saw it. An update
that raises is undone and gives an Event ``internal_error``.
"""

from __future__ import annotations

import json
import math
import time
from typing import Any, SupportsIndex

import numpy as np
import pytest
from sim_inputs import Run

from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World
from rlutf.sim import make_building
from schemas import InitialPose, LaserScan, Odometry, Relocalize
from service.engine import FleetEngine, Outbound
from service.guard import Limits, reach, region_on
from service.keys import Keys

WORLD = make_building(np.random.default_rng(11))
STEPS = 8


def _engine(limits: Limits | None = None) -> FleetEngine:
    engine = FleetEngine(Keys(), LocalizerConfig(), event_interval_ns=0, limits=limits)
    engine.register_map("m1", 1, WORLD, Run.received(0) - 10)
    return engine


def _start(engine: FleetEngine, run: Run) -> None:
    t = run.truth[0]
    engine.handle("r1", run.odometry(0), Run.received(0))
    start = InitialPose(
        stamp_ns=Run.stamp(0), map_id="m1", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    engine.handle("r1", start, Run.received(0) + 1)


def _poses(out: list[Outbound]) -> list[bytes]:
    return [o.payload for o in out if o.kind == "pose"]


def _events(out: list[Outbound]) -> list[dict[str, Any]]:
    return [json.loads(o.payload) for o in out if o.kind == "event"]


def _scan(run: Run, i: int, **change: Any) -> LaserScan:
    return LaserScan.model_validate({**run.scan(i).model_dump(), **change})


def _bad_inputs(run: Run, i: int) -> list[tuple[str, Any]]:
    """Schema-valid inputs over a default limit, with the field their Event must name."""
    stamp = Run.stamp(i)
    n = len(run.scan(i).ranges)
    return [
        ("angle_increment", _scan(run, i, angle_increment=5e-324)),
        ("angle_increment", _scan(run, i, angle_increment=1e300)),
        ("angle_min", _scan(run, i, angle_min=1e308)),
        ("sensor_offset.x", _scan(run, i, sensor_offset={"x": 1e308, "y": 0, "theta": 0})),
        ("sensor_offset.y", _scan(run, i, sensor_offset={"x": 0, "y": -1e200, "theta": 0})),
        ("sensor_offset.theta", _scan(run, i, sensor_offset={"x": 0, "y": 0, "theta": -1e300})),
        ("ranges", _scan(run, i, ranges=[3.0] * 8000, angle_increment=2 * math.pi / 8000)),
        ("x", Odometry(stamp_ns=stamp, x=1e308, y=0.0, theta=0.0)),
        ("y", Odometry(stamp_ns=stamp, x=0.0, y=-1e15, theta=0.0)),
        ("theta", Odometry(stamp_ns=stamp, x=0.0, y=0.0, theta=1e308)),
        ("x", InitialPose(stamp_ns=stamp, map_id="m1", x=1e308, y=0.0, theta=0.0)),
        ("theta", InitialPose(stamp_ns=stamp, map_id="m1", x=1.0, y=1.0, theta=-1e200)),
        (
            "region.radius",
            Relocalize(stamp_ns=stamp, map_id="m1", region={"x": 0, "y": 0, "radius": 1e308}),
        ),
        (
            "region.x",
            Relocalize(stamp_ns=stamp, map_id="m1", region={"x": 1e300, "y": 0, "radius": 1}),
        ),
    ][: None if n else 0]


def test_inputs_over_a_limit_give_an_event_and_change_nothing() -> None:
    run = Run.make(WORLD, 3, STEPS)
    plain, attacked = _engine(Limits(max_beams=4096)), _engine(Limits(max_beams=4096))
    _start(plain, run)
    _start(attacked, run)
    seen: list[dict[str, Any]] = []
    for i in range(1, STEPS + 1):
        expected = plain.handle("r1", run.odometry(i), Run.received(i))
        got = attacked.handle("r1", run.odometry(i), Run.received(i))
        for field, bad in _bad_inputs(run, i):
            out = attacked.handle("r1", bad, Run.received(i))
            assert [o.kind for o in out] == ["rejected", "event"], (field, out)
            (event,) = _events(out)
            assert event["code"] == "invalid_message" and event["level"] == "error"
            assert f"{type(bad).__name__}.{field}" in event["message"], event
            assert "limits." in event["message"]
            seen.append(event)
        scan = run.scan(i)
        expected += plain.handle("r1", scan, Run.received(i) + 1)
        got += attacked.handle("r1", scan, Run.received(i) + 1)
        assert _poses(got) == _poses(expected), f"step {i}: a rejected input changed the robot"
    assert len(seen) == STEPS * len(_bad_inputs(run, 1))


def test_a_scan_of_ranges_far_beyond_the_map_costs_nothing_after_an_initial_pose() -> None:
    # Issue 19: ranges of 1e5 m (range_max 1e6) ran the wide search over ~260,000 headings.
    run = Run.make(WORLD, 4, 2)
    engine = _engine()
    _start(engine, run)
    engine.handle("r1", run.odometry(1), Run.received(1))
    far = _scan(run, 1, ranges=[1e5] * len(run.scan(1).ranges), range_max=1e6)
    t0 = time.perf_counter()
    out = engine.handle("r1", far, Run.received(1) + 1)
    assert time.perf_counter() - t0 < 1.0
    assert [e["code"] for e in _events(out)] == ["lost"]  # no return left: nothing to compare
    # The robot is fine: the next real scan is tracked.
    engine.handle("r1", run.odometry(2), Run.received(2))
    (pose,) = _poses(engine.handle("r1", run.scan(2), Run.received(2) + 1))
    p = json.loads(pose)
    assert p["status"] != "lost"
    assert math.hypot(p["x"] - run.truth[2][0], p["y"] - run.truth[2][1]) < 0.3


def test_far_ranges_mixed_with_real_ones_are_no_return() -> None:
    """A few beams of 1e5 m among real ones: the real ones localize, as if the far were null."""
    run = Run.make(WORLD, 5, 3)
    with_far, with_null = _engine(), _engine()
    for engine in (with_far, with_null):
        _start(engine, run)
    for i in range(1, 4):
        scan = run.scan(i)
        ranges = list(scan.ranges)
        far = [*ranges]
        null = [*ranges]
        for j in range(0, len(ranges), 7):
            far[j], null[j] = 1e5, None
        a = with_far.handle("r1", run.odometry(i), Run.received(i))
        a += with_far.handle("r1", _scan(run, i, ranges=far, range_max=1e6), Run.received(i) + 1)
        b = with_null.handle("r1", run.odometry(i), Run.received(i))
        b += with_null.handle("r1", _scan(run, i, ranges=null, range_max=1e6), Run.received(i) + 1)
        assert _poses(a) == _poses(b)


def test_reach_is_the_map_diagonal_capped_by_the_setting() -> None:
    x0, y0, x1, y1 = WORLD.bounds
    diagonal = math.hypot(x1 - x0, y1 - y0)
    assert reach(WORLD, (0.0, 0.0), Limits()) == pytest.approx(diagonal + 1.0)
    assert reach(WORLD, (3.0, 4.0), Limits()) == pytest.approx(diagonal + 6.0)
    assert reach(WORLD, (0.0, 0.0), Limits(max_range=2.0)) == 2.0


def test_a_region_larger_than_the_map_is_the_whole_map() -> None:
    x0, y0, x1, y1 = WORLD.bounds
    centre = ((x0 + x1) / 2, (y0 + y1) / 2)
    assert region_on((*centre, 1e6), WORLD) is None
    assert region_on((*centre, 1.0), WORLD) == (*centre, 1.0)
    assert region_on(None, WORLD) is None


def test_a_failing_update_is_undone_and_gives_an_internal_error_event() -> None:
    # With the sensor-offset limit lifted, an offset of 1e308 overflows inside the update.
    loose = Limits(max_sensor_offset=1e308)
    run = Run.make(WORLD, 6, STEPS)
    plain, attacked = _engine(loose), _engine(loose)
    _start(plain, run)
    _start(attacked, run)
    for i in range(1, STEPS + 1):
        expected = plain.handle("r1", run.odometry(i), Run.received(i))
        got = attacked.handle("r1", run.odometry(i), Run.received(i))
        bad = _scan(run, i, sensor_offset={"x": 1e308, "y": 0.0, "theta": 0.0})
        out = attacked.handle("r1", bad, Run.received(i))
        (event,) = _events(out)
        assert event["code"] == "internal_error" and event["level"] == "error"
        assert event["key"] == "rlutf/robots/r1/scan"
        assert f"scan {bad.stamp_ns} not applied" in event["message"]
        assert "state is as before" in event["message"]
        scan = run.scan(i)  # simulated with noise: one scan for both engines
        expected += plain.handle("r1", scan, Run.received(i) + 1)
        got += attacked.handle("r1", scan, Run.received(i) + 1)
        assert _poses(got) == _poses(expected), f"step {i}: the failed update left a trace"


class _FailingList(list[np.ndarray]):
    """A robot's odometry poses whose next insert fails (out of memory, say)."""

    def insert(self, index: SupportsIndex, value: np.ndarray) -> None:
        raise MemoryError("no room")


def test_a_failing_odometry_reading_leaves_no_trace() -> None:
    # Odometry is applied without a snapshot (half of the inputs): all or nothing by itself.
    run = Run.make(WORLD, 6, STEPS)
    plain, attacked = _engine(), _engine()
    _start(plain, run)
    _start(attacked, run)
    robot = attacked._robots["r1"]
    stamps, poses = list(robot.odom_stamps), robot.odom_poses
    robot.odom_poses = _FailingList(poses)
    out = attacked.handle("r1", run.odometry(1), Run.received(1))
    (event,) = _events(out)
    assert event["code"] == "internal_error" and event["key"] == "rlutf/robots/r1/odom"
    assert robot.odom_stamps == stamps and list(robot.odom_poses) == poses
    robot.odom_poses = list(robot.odom_poses)
    for i in range(1, STEPS + 1):
        expected = plain.handle("r1", run.odometry(i), Run.received(i))
        got = attacked.handle("r1", run.odometry(i), Run.received(i))
        scan = run.scan(i)
        expected += plain.handle("r1", scan, Run.received(i) + 1)
        got += attacked.handle("r1", scan, Run.received(i) + 1)
        assert _poses(got) == _poses(expected), f"step {i}: the failed reading left a trace"


def test_limits_are_settings_and_recorded_for_replay() -> None:
    from service.config import Settings
    from service.logs.replayconfig import resolve

    settings = Settings(limits={"max_range": 50.0})  # type: ignore[arg-type]
    assert settings.effective()["limits"]["max_range"] == 50.0
    config = resolve(settings.effective())
    assert config.limits.max_range == 50.0
    assert resolve(None).limits == Limits()
    with pytest.raises(ValueError):
        Limits(max_beams=100_000)


def test_a_map_world_is_shared_not_copied_by_the_snapshot() -> None:
    # A relocalizing robot's snapshot deep-copies its relocalization, not the map.
    from service.guard import Snapshot

    run = Run.make(WORLD, 7, 2)
    engine = _engine()
    _start(engine, run)
    engine.handle("r1", Relocalize(stamp_ns=Run.stamp(1), map_id="m1"), Run.received(1))
    robot = engine._robots["r1"]
    assert robot.localizer is not None and robot.localizer.relocalizing
    snap = Snapshot(robot)
    follower = snap.loc_fields["_follower"]
    assert follower is not robot.localizer._follower
    assert follower.world is WORLD
    assert isinstance(WORLD, World)
