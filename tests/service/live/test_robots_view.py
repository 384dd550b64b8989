"""``{prefix}/service/{instance}/robots`` of a real service, asked over a real client session."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable

import pytest
from service_harness import Bench, Collector, drive

from schemas import Event, RobotsAnswer, RobotState, WaitingRobot, encode
from service.live.robots import (
    MAX_WAITING,
    RobotView,
    merge_robots,
    merge_waiting,
    one_sigma,
)

pytestmark = pytest.mark.integration


def ask(bench: Bench, key: str) -> list[dict]:
    return [
        json.loads(r.ok.payload.to_bytes())
        for r in bench.client.get(key, timeout=2.0)
        if r.ok is not None
    ]


def test_answers_every_robot_held_with_its_latest_pose(bench: Bench) -> None:
    me = bench.service.settings.instance
    # before any robot: one answer, no robots
    (empty,) = ask(bench, "rlutf/service/*/robots")
    assert empty["instance"] == me and empty["robots"] == []

    asked = time.time_ns()
    last = drive(bench, ["r2", "r1"], 8)
    (answer,) = ask(bench, f"rlutf/service/{me}/robots")
    assert answer["instance"] == me
    assert answer["stamp_ns"] >= asked
    robots = answer["robots"]
    assert [r["robot_id"] for r in robots] == ["r1", "r2"]  # by robot id
    for r in robots:
        pose = last[r["robot_id"]]
        assert r["map_id"] == "m1"
        assert r["status"] == pose["status"] in ("tracking", "corrected", "lost")
        assert (r["x"], r["y"], r["theta"]) == (pose["x"], pose["y"], pose["theta"])
        assert r["owner"] == me
        assert r["localization_score"] == pose["localization_score"]
        assert r["deviation_range"] == pose["deviation_range"] > 0.0
        assert 0 <= r["age_s"] < 5.0
        assert 0 < r["latency_ms"] < 1000.0
        assert (r["sigma_xy_m"], r["sigma_theta_rad"]) == one_sigma(pose.get("covariance"))
        assert r["sigma_xy_m"] is not None and 0 < r["sigma_xy_m"] < 1.0
    # ages grow with the instance's clock while no scan comes
    time.sleep(0.3)
    (later,) = ask(bench, "rlutf/service/*/robots")
    for before, after in zip(robots, later["robots"], strict=True):
        assert after["age_s"] >= before["age_s"] + 0.25
        assert after["latency_ms"] == before["latency_ms"]
    # the answer reads as the client's model
    assert [s.robot_id for s in RobotsAnswer.model_validate(later).robots] == ["r1", "r2"]


def test_health_reports_the_recorder_queue(bench: Bench) -> None:
    (health,) = ask(bench, "rlutf/service/*/health")
    assert health["extra"]["recorder_queue"] == 0  # recording is off in the harness


def _state(robot: str, age: float | None, owner: str, x: float = 0.0) -> RobotState:
    return RobotState(
        robot_id=robot,
        map_id="m",
        status="tracking",
        x=x,
        y=-1.5,
        theta=math.pi / 2,
        age_s=age,
        latency_ms=None if age is None else 2.25,
        owner=owner,
        localization_score=None if age is None else 0.97,
        deviation_range=None if age is None else 0.0042,
    )


def test_merge_keeps_one_line_per_robot_the_fresher_pose() -> None:
    a = RobotsAnswer(
        instance="a", stamp_ns=1, robots=[_state("r2", 0.5, "a"), _state("r1", None, "a")]
    )
    b = RobotsAnswer(
        instance="b", stamp_ns=1, robots=[_state("r2", 0.1, "b"), _state("r1", 3.0, "b")]
    )
    merged = merge_robots([a, b])
    assert [(s.robot_id, s.owner) for s in merged] == [("r1", "b"), ("r2", "b")]
    assert [(s.robot_id, s.owner) for s in merge_robots([b, a])] == [("r1", "b"), ("r2", "b")]


def test_one_sigma_is_the_larger_axis_and_the_heading() -> None:
    assert one_sigma(None) == (None, None)
    assert one_sigma([1.0, 0.0]) == (None, None)
    sxy, sth = one_sigma([0.0004, 0, 0, 0, 0.0001, 0, 0, 0, 0.0009])
    assert sxy == pytest.approx(0.02) and sth == pytest.approx(0.03)
    # an ellipse at 45 degrees: variances 0.5 each, covariance 0.3 -> axes 0.8 and 0.2
    sxy, _ = one_sigma([0.5, 0.3, 0, 0.3, 0.5, 0, 0, 0, 0.0])
    assert sxy == pytest.approx(math.sqrt(0.8))
    # variances at the end of the float range overflow: no figure, rather than an infinity the
    # answer's model refuses (the answer wrote null there before it had one)
    assert one_sigma([1e308, 0, 0, 0, 1e308, 0, 0, 0, 4.0]) == (None, 2.0)


def _event(code: str) -> bytes:
    return encode(Event(stamp_ns=1, level="warning", code=code, key="k", message="m"))


def test_the_view_remembers_a_bounded_number_of_waiting_robots() -> None:
    now = [10**18]
    poses: dict[str, bytes] = {}
    view = RobotView("a", poses, lambda: now[0])
    view.event("r1", _event("not_initialized"), now[0])
    view.event("r2", _event("lost"), now[0])  # not a reason to wait
    now[0] += 2_000_000_000
    view.event("r3", _event("map_not_found"), now[0])
    waiting = view.waiting()
    assert [(w.robot_id, w.reason, w.age_s) for w in waiting] == [
        ("r1", "not_initialized", 2.0),
        ("r3", "map_not_found", 0.0),
    ]
    poses["r1"] = b"{}"  # r1 got a pose: no longer waiting
    assert [w.robot_id for w in view.waiting()] == ["r3"]
    for i in range(MAX_WAITING + 10):
        view.event(f"x{i}", _event("not_initialized"), now[0])
    ids = {w.robot_id for w in view.waiting()}
    assert len(ids) == MAX_WAITING and "x0" not in ids and f"x{MAX_WAITING + 9}" in ids


def test_merge_waiting_leaves_out_robots_with_a_pose() -> None:
    def wait(robot: str, age: float, owner: str) -> WaitingRobot:
        return WaitingRobot(robot_id=robot, reason="not_initialized", age_s=age, owner=owner)

    a = RobotsAnswer(
        instance="a", stamp_ns=1, robots=[_state("r1", 0.1, "a")], waiting=[wait("r2", 3, "a")]
    )
    b = RobotsAnswer(instance="b", stamp_ns=1, waiting=[wait("r1", 1, "b"), wait("r2", 1, "b")])
    assert [(w.robot_id, w.owner) for w in merge_waiting([a, b])] == [("r2", "b")]


def test_a_robot_scanning_without_an_initial_pose_is_listed_as_waiting(bench: Bench) -> None:
    bench.put_map()
    robot = bench.robot("r9", 3)
    robot.odom(0)
    answer: dict = {}
    for _ in range(50):  # until the service has turned a scan into a not_initialized Event
        robot.advance()
        (answer,) = ask(bench, "rlutf/service/*/robots")
        if answer["waiting"]:
            break
        time.sleep(0.05)
    assert answer["robots"] == []
    (w,) = answer["waiting"]
    assert (w["robot_id"], w["reason"]) == ("r9", "not_initialized")
    assert 0 <= w["age_s"] < 5
    assert w["owner"] == bench.service.settings.instance


def test_a_robot_given_an_initial_pose_waits_for_its_first_scan_in_the_view() -> None:
    now = [10**18]
    poses: dict[str, bytes] = {"r1": b"{}"}
    view = RobotView("a", poses, lambda: now[0])
    view.initialized("r1", now[0], "m1")  # re-initialized while tracking: it has a pose
    view.initialized("r2", now[0], "m1")
    now[0] += 1_500_000_000
    view.initialized("r3", now[0], "typo")
    view.event("r3", _event("map_not_found"), now[0])  # refused: the Event says why
    view.told("r4", "map_not_found", now[0])  # a robot's own scans wait for a map: none named
    assert [(w.robot_id, w.reason, w.age_s, w.map_id) for w in view.waiting()] == [
        ("r2", "no_scan_yet", 1.5, "m1"),
        ("r3", "map_not_found", 0.0, "typo"),  # the map it waits for, from its initial pose
        ("r4", "map_not_found", 0.0, None),
    ]
    poses["r2"] = b"{}"
    assert [w.robot_id for w in view.waiting()] == ["r3", "r4"]


def test_a_robot_whose_scans_have_no_returns_is_not_listed_as_sending_none() -> None:
    # A blocked lidar: every scan "lost: too few returns", no pose ever published. The view
    # listed it as "no scan yet" (is it sending scans?), sending the operator to the network.
    from service.keys import NO_RETURNS_MESSAGE

    now = [10**18]
    poses: dict[str, bytes] = {"r2": b"{}"}
    view = RobotView("a", poses, lambda: now[0])
    view.initialized("r1", now[0], "m1")
    lost = encode(
        Event(stamp_ns=now[0], level="warning", code="lost", key="rlutf/robots/r1/scan",
              message=NO_RETURNS_MESSAGE)
    )  # fmt: skip
    now[0] += 10**9
    view.event("r1", lost, now[0])
    view.event("r2", lost, now[0])  # tracking until now: its pose ages in the view instead
    assert [(w.robot_id, w.reason, w.map_id) for w in view.waiting()] == [
        ("r1", "no_returns", "m1")
    ]


def test_an_initial_pose_before_any_scan_lists_the_robot_until_its_first_pose(
    bench: Bench,
) -> None:
    bench.put_map()
    time.sleep(0.3)
    robot = bench.robot("r7", 4)
    robot.initial_pose("m1")
    answer: dict = {}
    for _ in range(40):
        (answer,) = ask(bench, "rlutf/service/*/robots")
        if answer["waiting"]:
            break
        time.sleep(0.05)
    (w,) = answer["waiting"]
    assert (w["robot_id"], w["reason"], w["owner"], w["map_id"]) == (
        "r7",
        "no_scan_yet",
        bench.service.settings.instance,
        "m1",
    )
    assert answer["robots"] == []
    for _ in range(60):  # its scans: a pose, and no longer waiting
        robot.advance()
        (answer,) = ask(bench, "rlutf/service/*/robots")
        if answer["robots"]:
            break
        time.sleep(0.05)
    assert [r["robot_id"] for r in answer["robots"]] == ["r7"] and answer["waiting"] == []


def test_an_initial_pose_the_engine_refuses_places_no_robot_in_the_view(bench: Bench) -> None:
    # An InitialPose over a limit (a pose 1e308 m out) is refused with an Event: the view once
    # listed the robot as placed ("no scan yet") all the same, and its next scan then got
    # not_initialized.
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/r8/events", col)
    bench.put_map()
    time.sleep(0.3)
    bench.robot("r8", 5).initial_pose("m1", offset=(1e308, 0.0, 0.0))
    assert col.wait_for(
        lambda: any(e["code"] == "invalid_message" for e in col.on("rlutf/robots/r8/events"))
    )
    sub.undeclare()
    (answer,) = ask(bench, "rlutf/service/*/robots")
    assert answer["waiting"] == [] and answer["robots"] == []


def test_a_robot_restored_after_a_restart_is_shown_by_its_owner_until_its_first_pose() -> None:
    from schemas import PoseEstimate

    now = [10**18]
    poses: dict[str, bytes] = {}
    view = RobotView("a", poses, lambda: now[0])
    view.owns = lambda robot: robot != "r3"  # r3 belongs to another instance now

    def parked(robot: str, x: float) -> PoseEstimate:
        return PoseEstimate(
            stamp_ns=now[0] - 90 * 10**9, robot_id=robot, map_id="m1", x=x, y=2.0,
            theta=0.1, status="tracking", discrepancy=0.01, iterations=0,
        )  # fmt: skip

    for robot, x in (("r1", 1.0), ("r2", 3.0), ("r3", 5.0)):
        view.restore(parked(robot, x), now[0] - 60 * 10**9)  # published a minute ago
    states = view.states()
    assert [(s.robot_id, s.x, s.status, s.age_s, s.latency_ms) for s in states] == [
        ("r1", 1.0, "tracking", 60.0, None),
        ("r2", 3.0, "tracking", 60.0, None),
    ]
    poses["r1"] = encode(parked("r1", 1.5))  # r1's first pose since the restart
    view.published("r1", now[0], now[0] - 2_000_000)
    assert [(s.robot_id, s.x, s.age_s) for s in view.states()] == [
        ("r1", 1.5, 0.0),
        ("r2", 3.0, 60.0),
    ]
    view.forget("r2")  # handed to another instance
    assert [s.robot_id for s in view.states()] == ["r1"]


def test_a_relocalize_before_any_scan_lists_the_robot_on_its_map(bench: Bench) -> None:
    # `rlutf relocalize r6 --map m1` for a robot that streams nothing yet: the view did not
    # list it at all (an initial pose did), and after a Relocalize on a map no storage has, a
    # second one on the right map left it listed as "no map" with no map.
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/r6/events", col)
    bench.put_map()
    time.sleep(0.3)

    def waiting() -> list[tuple[str, str, str | None]]:
        (answer,) = ask(bench, "rlutf/service/*/robots")
        return [(w["robot_id"], w["reason"], w["map_id"]) for w in answer["waiting"]]

    def relocalize(map_id: str) -> None:
        payload = json.dumps({"stamp_ns": time.time_ns(), "map_id": map_id}).encode()
        bench.client.put("rlutf/robots/r6/relocalize", payload)

    relocalize("m1")
    assert col.wait_for(lambda: waiting() == [("r6", "no_scan_yet", "m1")], 5.0), waiting()
    relocalize("typo")
    assert col.wait_for(lambda: waiting() == [("r6", "map_not_found", "typo")], 5.0), waiting()
    relocalize("m1")
    assert col.wait_for(lambda: waiting() == [("r6", "no_scan_yet", "m1")], 5.0), waiting()
    sub.undeclare()


def test_a_robot_whose_clock_is_ahead_is_listed_as_such_not_as_sending_no_scan(
    bench: Bench,
) -> None:
    # A robot whose clock is an hour ahead, placed by an operator (the pose stamped with the
    # operator's clock, taken in): every scan of its own is refused (stamp_rejected). The view
    # listed it as "no scan yet" (is it sending scans?), sending the operator to the network.
    bench.put_map()
    time.sleep(0.3)
    robot = bench.robot("r8", 5)
    robot.initial_pose("m1")
    robot.t0 += 3_600 * 10**9  # its clock, for its scans and odometry from now on

    def waiting() -> list[tuple[str, str, object]]:
        answers = ask(bench, "rlutf/service/*/robots")
        return [(w["robot_id"], w["reason"], w["map_id"]) for a in answers for w in a["waiting"]]

    for _ in range(40):
        robot.advance()
        if waiting() == [("r8", "stamp_rejected", "m1")]:
            break
        time.sleep(0.05)
    assert waiting() == [("r8", "stamp_rejected", "m1")]


def test_a_tracking_robot_whose_clock_jumps_ahead_is_said_refused_not_silent(
    bench: Bench,
) -> None:
    # A robot tracking on its map whose clock steps an hour ahead (a bad NTP server): every
    # input of it is refused (stamp_rejected) while it sends at 10 Hz, and the view showed its
    # last pose ageing, "silent" as a robot that stopped sending.
    bench.put_map()
    time.sleep(0.3)
    robot = bench.robot("r9", 6)
    robot.initial_pose("m1")
    time.sleep(0.3)

    def state() -> dict:
        answers = ask(bench, "rlutf/service/*/robots")
        return next((r for a in answers for r in a["robots"] if r["robot_id"] == "r9"), {})

    for _ in range(5):
        robot.advance()
        time.sleep(0.05)
    assert wait_until_state(state, lambda s: bool(s) and s.get("refused") is None)
    robot.t0 += 3_600 * 10**9
    for _ in range(40):
        robot.advance()
        if state().get("refused") == "stamp_rejected":
            break
        time.sleep(0.05)
    assert state().get("refused") == "stamp_rejected"
    robot.t0 -= 3_600 * 10**9  # its clock set right: its poses come again, and it is not said
    assert wait_until_state(state, lambda s: bool(s) and s.get("refused") is None, robot.advance)


def wait_until_state(
    state: Callable[[], dict],
    ok: Callable[[dict], bool],
    each: Callable[[], object] = lambda: None,
) -> bool:
    """Whether ``ok(state())`` came true within 60 tries, ``each()`` before each."""
    for _ in range(60):
        each()
        if ok(state()):
            return True
        time.sleep(0.05)
    return False
