"""Followed poses of made-up robot ids give way to newer ones once ``max_robots`` are held.

Any client may put poses (with no access control). Poses on ``max_robots`` made-up robot ids
were followed and kept for good (only a robot this instance held and evicted was forgotten),
and from then on no new robot's pose was followed, this instance's own included: a robot
handed over to it later had no seed. Found by a reviewer reading what the poses followed are
bounded by, after the flood of made-up ids on input keys.
"""

from __future__ import annotations

import threading

from schemas.fastpose import encode_pose
from service.cluster.followed import FollowedPoses

LIMIT = 1_000_000
NOW = 100_000_000_000


def _payload(robot: str, stamp: int) -> bytes:
    return encode_pose(stamp, robot, "m1", 1.0, 2.0, 0.3, "tracking", 0.01, 2, [0.0] * 9)


def test_a_newer_robots_pose_takes_the_place_of_the_stalest_made_up_one() -> None:
    f = FollowedPoses(lambda: NOW, threading.RLock())
    f.max_ahead_ns = 1_000_000_000
    f.max_robots = 3
    for i in range(3):  # a flood of forged poses, stamped a while ago
        f.follow(f"fake{i}", _payload(f"fake{i}", NOW - 10_000_000_000 + i), LIMIT)
    f.follow("r1", _payload("r1", NOW), LIMIT)
    assert f.holds("r1") and not f.holds("fake0")
    f.follow_own("r2", _payload("r2", NOW), NOW)
    assert f.holds("r2") and not f.holds("fake1")
    seed = f.newest("r1")
    assert seed is not None and seed.stamp_ns == NOW
    assert f.replaced == 2
    # a pose no newer than every one held takes no place
    f.follow("late", _payload("late", NOW - 20_000_000_000), LIMIT)
    assert not f.holds("late") and f.holds("fake2")


def test_the_stalest_pose_is_found_without_a_walk_over_every_pose() -> None:
    """A walk over every pose held for each new robot would cost a flood of forged poses on
    new ids milliseconds each under the ownership's lock; the heap of stamps stays within a
    few times the poses held, however often they are updated."""
    f = FollowedPoses(lambda: NOW, threading.RLock())
    f.max_robots = 1000
    for i in range(1000):
        f.follow(f"r{i}", _payload(f"r{i}", NOW - 1000 + i), LIMIT)
    for k in range(20):  # every robot updated twenty times
        for i in range(1000):
            f.follow(f"r{i}", _payload(f"r{i}", NOW + k * 1000 + i), LIMIT)
    assert len(f._ages) <= 4 * 1000 + 64 + 1
    f.follow("new", _payload("new", NOW + 10**6), LIMIT)
    assert f.holds("new") and not f.holds("r0") and f.holds("r1")
