"""The service's poses scored against a simulated fleet's truth: error, latency, status.

A pose names the stamp of the scan it answers; the fleet stamps step ``k`` at
``t0 + k * period``, so the stamp gives the step and the plan the truth there. Thread-safe:
poses arrive on Zenoh's callback thread while the fleet sends and a view reads.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from rlutf.motion import wrap_scalar
from schemas import PoseEstimate, SchemaError, decode
from service.sim.plan import FleetPlan

#: Scans awaiting their pose, at most (the older half is forgotten past it).
FORGET_AFTER = 100_000


@dataclass
class RobotScore:
    """What is known of one robot's poses so far."""

    robot_id: str
    sent: int = 0
    errors: list[float] = field(default_factory=list)
    heading_errors: list[float] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    statuses: dict[str, int] = field(default_factory=dict)
    last_status: str = "-"
    last_sigma: tuple[float, float] = (math.nan, math.nan)
    last_odometry_error: float = 0.0

    @property
    def poses(self) -> int:
        """Poses received."""
        return len(self.errors)

    def latency_ms(self, q: float) -> float:
        """The ``q``-th percentile of the scan-to-pose latency, ms (``nan`` before any)."""
        return float(np.percentile(self.latencies_ms, q)) if self.latencies_ms else math.nan


def sigma(covariance: tuple[float, ...] | None) -> tuple[float, float]:
    """One-sigma position (cm, the root of the position covariance's trace) and heading (deg)
    of a PoseEstimate's covariance; NaN without one."""
    if covariance is None:
        return (math.nan, math.nan)
    position = math.sqrt(max(covariance[0] + covariance[4], 0.0)) * 100
    return (position, math.degrees(math.sqrt(max(covariance[8], 0.0))))


class Scoreboard:
    """Scores of a plan's robots, their steps stamped ``t0_ns + step * period``.

    Args:
        plan: the fleet.
        t0_ns: the stamp of step 0.
    """

    def __init__(self, plan: FleetPlan, t0_ns: int) -> None:
        self.plan, self.t0_ns = plan, t0_ns
        self.period_ns = plan.spec.period_ns
        self.robots = {r.robot_id: RobotScore(r.robot_id) for r in plan.robots}
        self._index = {r.robot_id: i for i, r in enumerate(plan.robots)}
        self._sent_at: dict[tuple[str, int], int] = {}
        self.lock = threading.Lock()

    def stamp(self, step: int) -> int:
        """The stamp of ``step``."""
        return self.t0_ns + step * self.period_ns

    def sent(self, robot: int, step: int, now_ns: int) -> None:
        """The robot's scan of ``step`` was put at ``now_ns``."""
        rid = self.plan.robots[robot].robot_id
        with self.lock:
            self.robots[rid].sent += 1
            self._sent_at[(rid, self.stamp(step))] = now_ns
            if len(self._sent_at) > FORGET_AFTER:  # scans never answered (dropped, or no pose)
                oldest = sorted(self._sent_at.values())[len(self._sent_at) // 2]
                self._sent_at = {k: t for k, t in self._sent_at.items() if t > oldest}

    def on_pose(self, payload: bytes, now_ns: int) -> PoseEstimate | None:
        """Score a pose received at ``now_ns``; returns it (``None``: not one of this fleet's)."""
        try:
            pose = decode(PoseEstimate, payload)
        except SchemaError:
            return None
        i = self._index.get(pose.robot_id)
        step, rest = divmod(pose.stamp_ns - self.t0_ns, self.period_ns)
        if i is None or rest or step < 0:
            return None
        robot = self.plan.robots[i]
        truth = robot.truth_at(step)
        odom = robot.odometry_at(step)
        odom_error = math.hypot(odom[0] - truth[0], odom[1] - truth[1])
        with self.lock:
            score = self.robots[pose.robot_id]
            score.errors.append(math.hypot(pose.x - truth[0], pose.y - truth[1]))
            score.heading_errors.append(abs(math.degrees(wrap_scalar(pose.theta - truth[2]))))
            sent = self._sent_at.pop((pose.robot_id, pose.stamp_ns), None)
            if sent is not None:
                score.latencies_ms.append((now_ns - sent) / 1e6)
            score.statuses[pose.status] = score.statuses.get(pose.status, 0) + 1
            score.last_status = pose.status
            score.last_sigma = sigma(pose.covariance)
            score.last_odometry_error = float(odom_error)
        return pose

    def snapshot(self) -> list[RobotScore]:
        """A copy of every robot's score."""
        with self.lock:
            return [
                RobotScore(
                    s.robot_id,
                    s.sent,
                    list(s.errors),
                    list(s.heading_errors),
                    list(s.latencies_ms),
                    dict(s.statuses),
                    s.last_status,
                    s.last_sigma,
                    s.last_odometry_error,
                )
                for s in self.robots.values()
            ]
