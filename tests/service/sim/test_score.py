"""Scoring the service's poses against the simulated truth."""

from __future__ import annotations

import math

import pytest

from schemas import PoseEstimate, encode
from service.sim.plan import FleetSpec, plan_fleet
from service.sim.score import Scoreboard, sigma

PLAN = plan_fleet(FleetSpec(robots=2, poses=5, beams=8, seed=1))
T0 = 1_732_300_000_000_000_000


def _pose(robot: str, step: int, dx: float = 0.0, **kw: object) -> bytes:
    r = next(r for r in PLAN.robots if r.robot_id == robot)
    x, y, theta = r.truth_at(step)
    fields = {"status": "tracking", "discrepancy": 0.0, "iterations": 1, **kw}
    stamp = T0 + step * PLAN.spec.period_ns
    return encode(
        PoseEstimate(
            stamp_ns=stamp, robot_id=robot, map_id="sim", x=x + dx, y=y, theta=theta, **fields
        )  # type: ignore[arg-type]
    )


def test_a_pose_is_scored_against_the_truth_at_its_stamp() -> None:
    board = Scoreboard(PLAN, T0)
    board.sent(1, 7, T0 + 10**9)  # step 7: on the way back
    assert board.on_pose(_pose("r001", 7, dx=0.03), T0 + 10**9 + 4_000_000) is not None
    score = {s.robot_id: s for s in board.snapshot()}["r001"]
    assert score.sent == 1 and score.poses == 1
    assert score.errors[0] == pytest.approx(0.03)
    assert score.latency_ms(50) == pytest.approx(4.0)
    assert score.last_status == "tracking" and score.statuses == {"tracking": 1}


def test_what_is_not_a_pose_of_the_fleet_is_not_scored() -> None:
    board = Scoreboard(PLAN, T0)
    assert board.on_pose(b"not json", T0) is None
    stranger = encode(
        PoseEstimate(
            stamp_ns=T0,
            robot_id="other",
            map_id="sim",
            x=0,
            y=0,
            theta=0,
            status="tracking",
            discrepancy=0.0,
            iterations=1,
        )
    )
    assert board.on_pose(stranger, T0) is None
    assert all(s.poses == 0 for s in board.snapshot())


def test_sigma_of_a_covariance() -> None:
    cov = (0.0004, 0, 0, 0, 0.0005, 0, 0, 0, math.radians(2) ** 2)
    position, heading = sigma(cov)
    assert position == pytest.approx(3.0) and heading == pytest.approx(2.0)
    assert all(math.isnan(v) for v in sigma(None))
