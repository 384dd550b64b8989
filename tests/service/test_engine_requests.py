"""FleetEngine: requests that name a map that is not loaded, and ambiguous places (WIRE.md v1.1).

A robot localized on a map keeps its pose and map while the request waits for its map; the
request applies at the first input for which the map is loaded, or is abandoned (Event
``map_not_found``) ``REQUEST_WAIT_NS`` after it was received. A robot with no pose waits.
"""

from __future__ import annotations

import json
import math

import numpy as np
from sim_inputs import Run

from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World
from rlutf.sim import make_building
from schemas import InitialPose, Odometry, Relocalize
from service.engine import FleetEngine, Outbound
from service.keys import Keys
from service.relocalization import REQUEST_WAIT_NS

WORLD = make_building(np.random.default_rng(11))
OTHER = make_building(np.random.default_rng(12))
STEPS = 12


def _engine() -> FleetEngine:
    engine = FleetEngine(Keys(), LocalizerConfig(), event_interval_ns=0)
    engine.register_map("m1", 1, WORLD, Run.received(0) - 10)
    return engine


def _placed(engine: FleetEngine, run: Run, robot: str = "r1") -> None:
    t = run.truth[0]
    engine.handle(robot, run.odometry(0), Run.received(0))
    start = InitialPose(
        stamp_ns=Run.stamp(0), map_id="m1", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    assert engine.handle(robot, start, Run.received(0) + 1) == []


def _step(engine: FleetEngine, run: Run, i: int, robot: str = "r1", at: int = 0) -> list[Outbound]:
    received = at or Run.received(i)
    engine.handle(robot, run.odometry(i), received)
    return engine.handle(robot, run.scan(i), received + 1)


def _pose(out: list[Outbound]) -> dict[str, object]:
    poses = [json.loads(o.payload) for o in out if o.kind == "pose"]
    assert len(poses) == 1, out
    return poses[0]


def _events(out: list[Outbound]) -> list[dict[str, object]]:
    return [json.loads(o.payload) for o in out if o.kind == "event"]


def _error(pose: dict[str, object], truth: np.ndarray) -> float:
    return math.hypot(float(pose["x"]) - truth[0], float(pose["y"]) - truth[1])  # type: ignore[arg-type]


def test_unknown_map_keeps_a_tracking_robot_on_its_map_until_abandoned() -> None:
    run = Run.make(WORLD, 1, STEPS)
    engine = _engine()
    _placed(engine, run)
    for i in range(1, 4):
        _pose(_step(engine, run, i))
    wrong = InitialPose(stamp_ns=Run.stamp(4), map_id="typo", x=1.0, y=1.0, theta=0.0)
    out = engine.handle("r1", wrong, Run.received(4))
    assert [(o.kind, o.map_id) for o in out] == [("need_map", "typo")]
    for i in range(4, 8):
        pose = _pose(_step(engine, run, i))
        assert pose["map_id"] == "m1"
        assert _error(pose, run.truth[i]) < 0.1
    # Past the wait, the request is dropped with an Event; the map appearing later changes nothing.
    late = Run.received(4) + REQUEST_WAIT_NS + 1
    out = _step(engine, run, 8, at=late)
    assert [e["code"] for e in _events(out)] == ["map_not_found"]
    assert "abandoned" in str(_events(out)[0]["message"])
    assert _pose(out)["map_id"] == "m1"
    engine.register_map("typo", 1, OTHER, late + 10)
    pose = _pose(_step(engine, run, 9, at=late + 100_000_000))
    assert pose["map_id"] == "m1"
    assert _error(pose, run.truth[9]) < 0.1


def test_a_relocalize_on_an_unknown_map_changes_nothing() -> None:
    run = Run.make(WORLD, 2, STEPS)
    engine = _engine()
    _placed(engine, run)
    reference = _engine()
    _placed(reference, run)
    ask = Relocalize(stamp_ns=Run.stamp(3), map_id="nowhere")
    for i in range(1, 8):
        if i == 3:
            out = engine.handle("r1", ask, Run.received(3) - 1)
            assert [o.kind for o in out] == ["need_map"]
        # Same poses, bit for bit, as a robot that was never asked: nothing was reset.
        rng_state = run.rng.bit_generator.state
        got = _pose(_step(engine, run, i))
        run.rng.bit_generator.state = rng_state
        assert got == _pose(_step(reference, run, i))


def test_a_relocalize_on_an_unknown_map_is_abandoned_and_the_robot_kept() -> None:
    run = Run.make(WORLD, 4, STEPS)
    engine = _engine()
    _placed(engine, run)
    for i in range(1, 3):
        _pose(_step(engine, run, i))
    ask = Relocalize(stamp_ns=Run.stamp(3), map_id="nowhere")
    assert [o.kind for o in engine.handle("r1", ask, Run.received(3))] == ["need_map"]
    late = Run.received(3) + REQUEST_WAIT_NS + 1
    out = _step(engine, run, 3, at=late)
    assert [e["code"] for e in _events(out)] == ["map_not_found"]
    assert "abandoned" in str(_events(out)[0]["message"])
    pose = _pose(out)
    assert pose["map_id"] == "m1" and pose["status"] != "lost" and "hypotheses" not in pose
    assert _error(pose, run.truth[3]) < 0.1
    engine.register_map("nowhere", 1, OTHER, late + 10)  # too late: nothing changes
    out = _step(engine, run, 4, at=late + 100_000_000)
    assert _events(out) == [] and _pose(out)["map_id"] == "m1"
    assert _error(_pose(out), run.truth[4]) < 0.1


def test_a_request_applies_once_its_map_is_loaded() -> None:
    run = Run.make(WORLD, 3, STEPS)
    engine = _engine()
    _placed(engine, run)
    _pose(_step(engine, run, 1))
    t = run.truth[2]
    moved = InitialPose(
        stamp_ns=Run.stamp(2), map_id="m2", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    engine.handle("r1", run.odometry(2), Run.received(2) - 10)
    assert [o.kind for o in engine.handle("r1", moved, Run.received(2) - 5)] == ["need_map"]
    assert _pose(_step(engine, run, 2))["map_id"] == "m1"
    engine.register_map("m2", 1, WORLD, Run.received(3) - 100)  # the same building, as m2
    for i in range(3, 7):
        pose = _pose(_step(engine, run, i))
        assert pose["map_id"] == "m2"
        assert _error(pose, run.truth[i]) < 0.1


def test_a_robot_with_no_pose_waits_for_its_map() -> None:
    run = Run.make(WORLD, 4, STEPS)
    engine = FleetEngine(Keys(), LocalizerConfig(), event_interval_ns=0)
    t = run.truth[0]
    engine.handle("r1", run.odometry(0), Run.received(0))
    start = InitialPose(
        stamp_ns=Run.stamp(0), map_id="m1", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    assert [o.kind for o in engine.handle("r1", start, Run.received(0) + 1)] == ["need_map"]
    late = Run.received(1) + 2 * REQUEST_WAIT_NS  # never abandoned: it has no other map
    out = _step(engine, run, 1, at=late)
    assert [o.kind for o in out] == ["skipped", "event"]
    assert [e["code"] for e in _events(out)] == ["map_not_found"]
    assert "not loaded yet" in str(_events(out)[0]["message"])
    engine.register_map("m1", 1, WORLD, late + 10)
    pose = _pose(_step(engine, run, 2, at=late + 100_000_000))
    assert pose["map_id"] == "m1"
    assert _error(pose, run.truth[2]) < 0.1


#: A corridor that looks the same after a half turn about its centre, but for a block on one
#: wall at mid-length: from one end, two places fit, until the block comes into view.
CORRIDOR = World.from_geojson(
    {
        "type": "Polygon",
        "coordinates": [
            [[0, 0], [40, 0], [40, 6], [0, 6], [0, 0]],
            [[19, 0.8], [21, 0.8], [21, 1.8], [19, 1.8], [19, 0.8]],
        ],
    }
)


def _relocalizing_in_corridor(
    steps: int, x_end: float
) -> tuple[FleetEngine, Run, np.ndarray, list[Outbound]]:
    """A robot driven along the corridor from x = 5 to ``x_end``, relocalized at its start:
    the engine, the run, its truth and what the Relocalize gave."""
    truth = np.zeros((steps + 1, 3))
    truth[:, 0] = np.linspace(5.0, x_end, steps + 1)
    truth[:, 1] = 3.0
    run = Run(CORRIDOR, truth, truth.copy(), np.random.default_rng(0), 360)
    engine = FleetEngine(Keys(), LocalizerConfig(), event_interval_ns=0)
    engine.register_map("c", 1, CORRIDOR, 0)
    engine.handle("r1", run.odometry(0), Run.received(0))
    out = engine.handle("r1", Relocalize(stamp_ns=Run.stamp(0), map_id="c"), Run.received(0) + 1)
    return engine, run, truth, out


def test_an_ambiguous_place_says_lost_with_hypotheses_until_one_wins() -> None:
    steps = 110
    engine, run, truth, out = _relocalizing_in_corridor(steps, 16.0)
    codes = [e["code"] for e in _events(out)]
    poses = []
    for i in range(1, steps + 1):
        out = _step(engine, run, i)
        codes += [e["code"] for e in _events(out)]
        poses.append(_pose(out))
    assert codes.count("relocalizing") == codes.count("ambiguous") == 1
    assert codes.count("relocalized") == 1 and "lost" not in codes
    assert codes.index("relocalizing") < codes.index("ambiguous") < codes.index("relocalized")
    won = next(i for i, p in enumerate(poses) if p["status"] != "lost")
    assert won >= 1  # the first scan cannot tell the two ends apart
    for p in poses[:won]:
        hyps = p["hypotheses"]
        assert isinstance(hyps, list) and len(hyps) >= 2
        assert (p["x"], p["y"]) == (hyps[0]["x"], hyps[0]["y"])
        assert abs(math.remainder(p["theta"] - hyps[0]["theta"], math.tau)) < 1e-9
        assert all(0.0 <= h["score"] <= 1.0 for h in hyps)
        # Both ends are candidates all along: the true place and its half-turn image.
        i = poses.index(p) + 1
        image = (40.0 - truth[i, 0], 6.0 - truth[i, 1])
        assert min(_error(h, truth[i]) for h in hyps) < 0.1
        assert min(math.hypot(h["x"] - image[0], h["y"] - image[1]) for h in hyps) < 0.1
    assert poses[won]["status"] == "corrected" and "hypotheses" not in poses[won]
    # Never a confident wrong answer: every pose that is not lost is at the truth.
    for i, p in enumerate(poses[won:], start=won + 1):
        assert p["status"] != "lost" and _error(p, truth[i]) < 0.05


def test_long_updates_are_foreseen_for_scheduling() -> None:
    run = Run.make(WORLD, 5, STEPS)
    engine = _engine()
    assert not engine.expects_long_update("r1", ["odom", "scan"])  # unknown robot
    _placed(engine, run)
    _pose(_step(engine, run, 1))
    assert not engine.expects_long_update("r1", ["odom", "scan"])  # tracking
    assert engine.expects_long_update("r1", ["relocalize", "odom", "scan"])
    engine.handle("r1", Relocalize(stamp_ns=Run.stamp(2), map_id="m1"), Run.received(2) - 5)
    assert engine.expects_long_update("r1", ["odom", "scan"])  # its next scan searches the map
    assert _pose(_step(engine, run, 2))["status"] == "corrected"
    assert not engine.expects_long_update("r1", ["odom", "scan"])  # found: tracking again
    elsewhere = Run(OTHER, run.truth, run.odom, run.rng)  # a scan of another building
    engine.handle("r1", run.odometry(3), Run.received(3))
    out = engine.handle("r1", elsewhere.scan(3), Run.received(3) + 1)
    assert _pose(out)["status"] == "lost"
    assert engine.expects_long_update("r1", ["odom", "scan"])


def test_an_initial_pose_long_after_the_last_odometry_anchors_on_the_next_reading() -> None:
    # A robot the service held before (its state restored after a restart, or a robot back
    # after a while) has odometry readings from long ago; an operator's pose of now arrives
    # before the robot's next reading (two sessions, or a ROS 2 subscription still being
    # discovered). The old reading is not the odometry at the pose: taken as its anchor, the
    # first scan's motion was the robot's whole odometry since then, and the robot was lost
    # metres away. The first reading after the pose anchors it instead.
    run = Run.make(WORLD, 3, STEPS)
    engine = _engine()
    old = Run.stamp(0) - 60 * 10**9
    reading = Odometry(stamp_ns=old, x=40.0, y=-25.0, theta=2.0)  # another odometry frame
    engine.handle("r1", reading, old + 1_000_000)
    t = run.truth[0]
    start = InitialPose(
        stamp_ns=Run.stamp(0), map_id="m1", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    engine.handle("r1", start, Run.received(0))
    for i in range(1, 6):  # the reading at the pose's stamp never came
        pose = _pose(_step(engine, run, i))
        assert pose["status"] != "lost"
        assert _error(pose, run.truth[i]) < 0.05, i
    # a first scan before any reading after the pose: no motion, and the next scans still
    # anchor on the first reading after the pose, not on the old one
    engine = _engine()
    engine.handle("r1", reading, old + 1_000_000)
    engine.handle("r1", start, Run.received(0))
    pose = _pose(engine.handle("r1", run.scan(0), Run.received(0) + 2))
    assert _error(pose, run.truth[0]) < 0.05
    for i in range(1, 6):
        pose = _pose(_step(engine, run, i))
        assert _error(pose, run.truth[i]) < 0.05, i


def test_an_initial_pose_during_a_relocalization_ends_it_with_an_event() -> None:
    # The operator places a robot that is being relocalized (theirs, or one a restart seeded
    # from a pose too old to resume from): the episode's `relocalizing` gets its end.
    steps = 4
    engine, run, truth, out = _relocalizing_in_corridor(steps, 6.0)
    assert [e["code"] for e in _events(out)] == ["relocalizing"]
    out = _step(engine, run, 1)
    assert _pose(out)["status"] == "lost"  # the corridor's two ends: not decided yet
    t = truth[1]
    placed = InitialPose(
        stamp_ns=Run.stamp(1), map_id="c", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    events = _events(engine.handle("r1", placed, Run.received(1) + 2))
    assert [e["code"] for e in events] == ["relocalized"]
    assert "ended by an initial pose" in str(events[0]["message"])
    assert "(5.250, 3.000, 0.000) on map 'c' after 1 scan(s)" in str(events[0]["message"])
    for i in range(2, steps + 1):  # tracked from the operator's pose, no second end
        out = _step(engine, run, i)
        assert _pose(out)["status"] != "lost" and _events(out) == []
        assert _error(_pose(out), truth[i]) < 0.05
    # Placed again with no relocalization under way: nothing to end.
    again = InitialPose(stamp_ns=Run.stamp(steps), map_id="c", x=5.0, y=3.0, theta=0.0)
    assert engine.handle("r1", again, Run.received(steps) + 2) == []


def test_an_initial_pose_stamped_ahead_of_a_robot_s_clock_anchors_its_odometry() -> None:
    # A robot whose clock is years behind (no NTP: it starts in 2001) is placed by an operator
    # (`rlutf initialpose` stamps the pose with the operator's clock). Every reading of the
    # robot is long before the pose, so none was its odometry at the pose, and none after it
    # would come until the robot's clock passed the pose's stamp: its odometry went unused,
    # silently, each scan localized with no motion (searched: `corrected`, never `tracking`).
    # The pose is taken as at the robot's first scan instead; its odometry is used from there.
    run = Run.make(WORLD, 3, STEPS)
    behind = Run.stamp(0) - 978_307_200 * 10**9  # the robot's clock reads 2001
    engine = _engine()

    def odometry(i: int) -> Odometry:
        o = run.odometry(i)
        return o.model_copy(update={"stamp_ns": o.stamp_ns - behind})

    engine.handle("r1", odometry(0), Run.received(0))
    t = run.truth[0]
    start = InitialPose(
        stamp_ns=Run.stamp(0), map_id="m1", x=float(t[0]), y=float(t[1]), theta=float(t[2])
    )
    engine.handle("r1", start, Run.received(0) + 1)
    statuses = []
    for i in range(1, 8):
        engine.handle("r1", odometry(i), Run.received(i))
        scan = run.scan(i)
        scan = scan.model_copy(update={"stamp_ns": scan.stamp_ns - behind})
        pose = _pose(engine.handle("r1", scan, Run.received(i) + 1))
        assert _error(pose, run.truth[i]) < 0.05, i
        statuses.append(pose["status"])
    assert statuses[1:] == ["tracking"] * 6, statuses
