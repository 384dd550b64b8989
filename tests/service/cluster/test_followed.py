"""The poses every instance follows for handovers (service.cluster.followed): kept as they came
when they are in this service's encoding, decoded when a seed needs one."""

from __future__ import annotations

import json
import logging
import threading

import pytest

from schemas import PoseEstimate, encode
from schemas.fastpose import encode_pose
from service.cluster.followed import FollowedPoses

LIMIT = 1_000_000
NOW = 10_000_000_000


def _followed() -> FollowedPoses:
    f = FollowedPoses(lambda: NOW, threading.RLock())
    f.max_ahead_ns = 1_000_000_000
    return f


def _payload(robot: str, stamp: int, x: float = 1.0) -> bytes:
    return encode_pose(stamp, robot, "m1", x, 2.0, 0.3, "tracking", 0.01, 2, [0.0] * 9)


def test_a_pose_in_the_service_encoding_is_decoded_only_when_a_seed_needs_it() -> None:
    f = _followed()
    assert f.follow("r1", _payload("r1", 5_000, x=1.0), LIMIT) is None
    assert f.follow("r1", _payload("r1", 7_000, x=3.0), LIMIT) is None
    assert f.follow("r1", _payload("r1", 6_000, x=9.0), LIMIT) is None  # older: not kept
    assert "r1" in f.encoded and "r1" not in f.poses  # nothing decoded yet
    pose = f.newest("r1")
    assert pose is not None and (pose.stamp_ns, pose.x) == (7_000, 3.0)
    assert f.poses["r1"] is pose and "r1" not in f.encoded  # decoded once, kept decoded
    assert f.newest("r1") is pose


def test_a_pose_in_another_encoding_is_decoded_as_it_comes() -> None:
    f = _followed()
    fields = json.loads(_payload("r1", 5_000))
    reordered = json.dumps(dict(reversed(list(fields.items())))).encode()  # another tool's
    assert f.follow("r1", reordered, LIMIT) is None
    assert "r1" in f.poses and "r1" not in f.encoded
    assert f.newest("r1") == PoseEstimate.model_validate(fields)
    # A newer one in the service's encoding replaces it; an older decoded one does not.
    f.follow("r1", _payload("r1", 6_000), LIMIT)
    f.remember(PoseEstimate.model_validate({**fields, "stamp_ns": 5_500}))
    newest = f.newest("r1")
    assert newest is not None and newest.stamp_ns == 6_000


def test_poses_of_another_robot_too_large_or_too_far_ahead_are_not_followed() -> None:
    f = _followed()
    assert f.follow("r1", _payload("r2", 5_000), LIMIT) is None  # r2's pose on r1's key
    assert f.follow("r1", _payload("r1", 5_000), 100) is None  # over the size limit
    assert not f.holds("r1")
    ahead = NOW + 5_000_000_000
    problem = f.follow("r1", _payload("r1", ahead), LIMIT)
    assert problem is not None and "5 s ahead" in problem
    assert not f.holds("r1") and f.rejected == 1


def test_a_pose_whose_head_is_the_service_encoding_and_rest_is_not_seeds_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    f = _followed()
    forged = _payload("r1", 5_000).replace(b'"status":"tracking"', b'"status":"flying"')
    assert f.follow("r1", forged, LIMIT) is None
    assert f.holds("r1")  # kept by its head, as any pose in the service's encoding
    with caplog.at_level(logging.WARNING):
        assert f.newest("r1") is None
    assert "unreadable" in caplog.text
    twice = _payload("r1", 5_000)[:-1] + b',"stamp_ns":9000}'  # a second stamp, read last
    f.follow("r1", twice, LIMIT)
    with caplog.at_level(logging.WARNING):
        assert f.newest("r1") is None
    assert "contradicts its head" in caplog.text


def test_own_poses_and_followed_ones_count_against_the_robot_bound() -> None:
    f = _followed()
    f.max_robots = 2
    f.follow_own("r1", _payload("r1", 10), 10)
    f.follow("r2", encode(PoseEstimate.model_validate_json(_payload("r2", 10))), LIMIT)
    f.follow("r3", _payload("r3", 10), LIMIT)  # two robots held already
    assert f.holds("r1") and f.holds("r2") and not f.holds("r3")
    f.forget("r1")
    f.follow("r3", _payload("r3", 10), LIMIT)
    assert f.holds("r3") and not f.holds("r1")
