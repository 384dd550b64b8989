"""``{prefix}/service/{instance}/robots`` of a real service, asked over a real client session."""

from __future__ import annotations

import json
import math
import time

import pytest
from service_harness import Bench, Collector

from service.live.robots import RobotsAnswer, RobotState, merge_robots, robots_table

pytestmark = pytest.mark.integration


def drive(bench: Bench, robot_ids: list[str], steps: int) -> dict[str, dict]:
    """Feed each robot ``steps`` scans; the last pose each robot got, by robot id."""
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/*/pose", col)
    bench.put_map()
    time.sleep(0.3)
    robots = [bench.robot(r, seed) for seed, r in enumerate(robot_ids, 1)]
    for r in robots:
        r.initial_pose("m1")
    time.sleep(0.3)
    for _ in range(steps):
        for r in robots:
            r.advance()
        time.sleep(0.03)
    for r in robots:
        key, last = f"rlutf/robots/{r.robot_id}/pose", r.stamp(r.step)
        assert col.wait_for(lambda k=key, s=last: any(p["stamp_ns"] == s for p in col.on(k)))
    sub.undeclare()
    return {r.robot_id: col.on(f"rlutf/robots/{r.robot_id}/pose")[-1] for r in robots}


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


def test_table_has_a_header_and_aligned_rows() -> None:
    text = robots_table([_state("r1", 0.123, "a", x=12.3456), _state("robot-22", None, "b")])
    header, first, second = text.splitlines()
    assert header.split() == [
        "robot",
        "map",
        "status",
        "x",
        "y",
        "theta",
        "score",
        "range",
        "m",
        "age",
        "s",
        "latency",
        "ms",
        "owner",
    ]
    assert first.split() == [
        "r1",
        "m",
        "tracking",
        "12.346",
        "-1.500",
        "1.571",
        "0.97",
        "0.004",
        "0.12",
        "2.2",
        "a",
    ]
    assert second.split() == [
        "robot-22",
        "m",
        "tracking",
        "0.000",
        "-1.500",
        "1.571",
        "-",
        "-",
        "-",
        "-",
        "b",
    ]
    assert len({line.index("tracking") for line in (first, second)}) == 1  # columns aligned
