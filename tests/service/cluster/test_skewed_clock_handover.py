"""A robot whose clock is years behind the operator's, handed over between instances.

The operator places the robot with `rlutf initialpose` (stamped with the operator's clock); the
robot stamps its scans, so its poses, 31 years earlier. Every instance follows the robot's
InitialPose and poses for the seed of a handover, and took the one with the later stamp: the
InitialPose, always. The new owner seeded the robot where it had been placed, long before, and
its first pose was lost metres away. Poses of the robot's owner put on the InitialPose's map
well after it now supersede it, whatever the stamps say.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
import zenoh
from service_harness import Collector, running_bench, storeless_service, wait_until

from schemas import InitialPose, encode
from service.cluster.membership import owner_of

pytestmark = pytest.mark.integration

BEHIND_NS = 978_307_200 * 10**9  # the robot's clock: 31 years behind


def test_a_robot_whose_clock_is_behind_is_handed_over_from_its_last_pose(
    tmp_path: Path,
) -> None:
    with running_bench(tmp_path) as b:
        second = storeless_service(b, "second")
        try:
            first = b.service.settings.instance
            rid = next(
                r
                for r in (f"r{k}" for k in range(64))
                if owner_of(r, [first, "second"]) == "second"
            )
            assert wait_until(lambda: not b.service.ownership.owns(rid), 5.0)
            col = Collector()
            key = f"rlutf/robots/{rid}/pose"
            sub = b.client.declare_subscriber(key, col)
            b.put_map()
            time.sleep(0.5)
            robot = b.robot(rid, 3)
            now = robot.t0
            robot.t0 = now - BEHIND_NS
            p = robot.truth[0]
            robot.odom(0)
            placed = InitialPose(
                stamp_ns=now, map_id="m1", x=float(p[0]), y=float(p[1]), theta=float(p[2])
            )
            json = zenoh.Encoding.APPLICATION_JSON
            b.client.put(f"rlutf/robots/{rid}/initialpose", encode(placed), encoding=json)
            time.sleep(0.5)
            for _ in range(40):  # 4 s of the robot's time, driven away from where it was placed
                robot.advance()
                time.sleep(0.06)
            assert col.wait_for(lambda: len(col.on(key)) >= 40)
            second.close()  # its robots go to the first instance, which followed them
            assert wait_until(lambda: b.service.ownership.owns(rid), 5.0)
            seen = len(col.on(key))
            for _ in range(3):
                robot.advance()
                time.sleep(0.1)
            assert col.wait_for(lambda: len(col.on(key)) >= seen + 3)
            after = col.on(key)[seen]
            truth = robot.plan.truth_at(round((after["stamp_ns"] - robot.t0) / 1e8))
            assert after["status"] != "lost", after
            assert math.hypot(after["x"] - truth[0], after["y"] - truth[1]) < 0.05
            sub.undeclare()
        finally:
            second.close()
