"""The durable pose state: its file, atomic writes, corrupt files, sharing, and resume seeds."""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path

import pytest

from schemas import InitialPose, Odometry, PoseEstimate, Relocalize, encode
from service.cluster.membership import Membership
from service.cluster.ownership import Ownership
from service.cluster.posestate import (
    FILE_NAME,
    ODOM_RING,
    PoseState,
    StateUnreadable,
    odometry_around,
    parse_state,
)
from service.keys import InputKind, Message

S = 1_000_000_000


def _pose(robot: str, stamp: int, x: float = 1.0) -> PoseEstimate:
    return PoseEstimate(
        stamp_ns=stamp, robot_id=robot, map_id="m1", x=x, y=2.0, theta=0.3,
        status="tracking", discrepancy=0.01, iterations=1,
        covariance=[1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5],
    )  # fmt: skip


def _odom(stamp: int, x: float) -> Odometry:
    return Odometry(stamp_ns=stamp, x=x, y=0.0, theta=0.0)


def _state(folder: Path, instance: str = "i1") -> PoseState:
    clock = itertools.count(10 * S, S)
    return PoseState(folder, instance, 3600.0, lambda: next(clock))


def _feed(state: PoseState, robot: str, pose_stamp: int, published: int) -> None:
    """Odometry every 0.1 s from 0 to 2 s, then a pose stamped ``pose_stamp``."""
    for i in range(21):
        state.odom(robot, i * S // 10, encode(_odom(i * S // 10, x=i / 10)))
    state.pose(robot, encode(_pose(robot, pose_stamp)), pose_stamp, published)


def test_round_trip_keeps_the_pose_and_the_odometry_around_its_stamp(tmp_path: Path) -> None:
    state = _state(tmp_path)
    assert state.open() == ([], [])
    _feed(state, "r1", pose_stamp=1_550_000_000, published=7 * S)
    _feed(state, "r2", pose_stamp=2 * S, published=8 * S)
    assert state.write()
    assert not state.write()  # nothing changed since: no write
    doc = json.loads((tmp_path / FILE_NAME).read_bytes())
    assert (doc["version"], doc["instance"], sorted(doc["robots"])) == (1, "i1", ["r1", "r2"])

    robots, skipped = parse_state((tmp_path / FILE_NAME).read_bytes())
    assert skipped == 0
    r1 = robots["r1"]
    assert r1.pose == _pose("r1", 1_550_000_000)
    assert r1.published_ns == 7 * S
    # the reading before, the one at or before the stamp, and the one after (to interpolate)
    assert [o.stamp_ns for o in r1.odometry] == [1_400_000_000, 1_500_000_000, 1_600_000_000]
    assert [o.x for o in r1.odometry] == [1.4, 1.5, 1.6]
    assert [o.stamp_ns for o in robots["r2"].odometry] == [1_900_000_000, 2 * S]

    again = _state(tmp_path)  # a restart reads the same back
    restored, problems = again.open()
    assert problems == []
    assert {r.pose.robot_id: r for r in restored} == robots
    again.close()
    state.close()


def test_odometry_around_a_stamp() -> None:
    readings = [(s, b"%d" % s) for s in (10, 20, 30, 40)]
    assert [s for s, _ in odometry_around(readings, 25)] == [10, 20, 30]
    assert [s for s, _ in odometry_around(readings, 40)] == [30, 40]
    assert [s for s, _ in odometry_around(readings, 10)] == [10, 20]
    assert [s for s, _ in odometry_around(readings, 5)] == [10]  # none before: the first after
    assert odometry_around([], 5) == []


def test_the_ring_is_bounded(tmp_path: Path) -> None:
    state = _state(tmp_path)
    for i in range(10 * ODOM_RING):
        state.odom("r1", i, encode(_odom(i, 0.0)))
    assert len(state._rings["r1"]) == ODOM_RING


def test_an_interrupted_write_leaves_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    state = _state(tmp_path)
    state.open()
    _feed(state, "r1", pose_stamp=S, published=S)
    assert state.write()
    before = (tmp_path / FILE_NAME).read_bytes()

    state.pose("r1", encode(_pose("r1", 2 * S, x=9.0)), 2 * S, 2 * S)
    real_fsync = os.fsync

    def power_cut(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", power_cut)
    assert not state.write()  # the error is counted, not raised
    assert state.write_errors == 1
    assert (tmp_path / FILE_NAME).read_bytes() == before
    assert list(tmp_path.glob("*.tmp")) == []  # its temporary file removed
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert state.write()  # retried at the next interval
    assert parse_state((tmp_path / FILE_NAME).read_bytes())[0]["r1"].pose.x == 9.0


def test_a_temporary_file_left_by_a_crash_is_ignored_and_removed(tmp_path: Path) -> None:
    state = _state(tmp_path)
    state.open()
    _feed(state, "r1", pose_stamp=S, published=S)
    state.write()
    good = (tmp_path / FILE_NAME).read_bytes()
    half = tmp_path / f".{FILE_NAME}.abc123.tmp"  # kill -9 between write and rename
    half.write_bytes(good[: len(good) // 2])
    restored, problems = _state(tmp_path).open()
    assert problems == []
    assert [r.pose.robot_id for r in restored] == ["r1"]
    assert not half.exists()


@pytest.mark.parametrize(
    "content",
    [b'{"version": 1, "robots": {"r1": {"pose": {"stamp', b"", b"\xff\xfe", b"[1, 2]", b"{}"],
)
def test_a_corrupt_file_starts_an_empty_state_with_a_problem(
    tmp_path: Path, content: bytes
) -> None:
    (tmp_path / FILE_NAME).write_bytes(content)
    state = _state(tmp_path)
    restored, problems = state.open()
    assert restored == []
    assert len(problems) == 1 and "unreadable" in problems[0]
    _feed(state, "r1", pose_stamp=S, published=S)
    assert state.write()  # replaced by a good one
    assert list(parse_state((tmp_path / FILE_NAME).read_bytes())[0]) == ["r1"]
    with pytest.raises(StateUnreadable):
        parse_state(content)


def test_a_bad_entry_costs_only_its_robot(tmp_path: Path) -> None:
    state = _state(tmp_path)
    state.open()
    _feed(state, "r1", pose_stamp=S, published=S)
    _feed(state, "r2", pose_stamp=S, published=S)
    state.write()
    doc = json.loads((tmp_path / FILE_NAME).read_bytes())
    doc["robots"]["r2"]["pose"]["x"] = "far"
    (tmp_path / FILE_NAME).write_text(json.dumps(doc))
    restored, problems = _state(tmp_path).open()
    assert [r.pose.robot_id for r in restored] == ["r1"]
    assert problems == [f"{tmp_path / FILE_NAME}: 1 invalid robot entries skipped"]


def test_an_unwritable_folder_is_a_problem_not_a_crash(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    state = _state(tmp_path / "file" / "state")  # a folder under a file cannot be made
    restored, problems = state.open()
    assert restored == [] and len(problems) == 1
    _feed(state, "r1", pose_stamp=S, published=S)
    assert not state.write()
    assert state.write_errors == 1
    state.close()


def test_instances_sharing_a_folder_keep_each_others_robots(tmp_path: Path) -> None:
    a, b = _state(tmp_path, "a"), _state(tmp_path, "b")
    a.open(), b.open()
    _feed(a, "r1", pose_stamp=S, published=S)
    _feed(a, "r2", pose_stamp=S, published=S)
    assert a.write()
    b.pose("r2", encode(_pose("r2", 2 * S, x=5.0)), 2 * S, 2 * S)  # r2 moved to b since
    b.pose("r3", encode(_pose("r3", 2 * S)), 2 * S, 2 * S)
    assert b.write()
    a.pose("r1", encode(_pose("r1", 3 * S, x=7.0)), 3 * S, 3 * S)
    assert a.write()
    robots = parse_state((tmp_path / FILE_NAME).read_bytes())[0]
    assert sorted(robots) == ["r1", "r2", "r3"]
    assert (robots["r1"].pose.x, robots["r2"].pose.x) == (7.0, 5.0)  # the newest of each


# ---------------------------------------------------------------------------- resume seeds
Admitted = list[tuple[str, InputKind, Message]]


def _ownership(max_age_s: float) -> tuple[Ownership, Admitted]:
    admitted: Admitted = []
    clock = itertools.count(1000 * S)
    own = Ownership(
        Membership("a"),
        lambda robot, kind, payload, msg, received: admitted.append((robot, kind, msg)),
        lambda: next(clock),
        tail_ns=5 * S,
        resume_max_age_ns=int(max_age_s * S),
    )
    own.ready = True
    return own, admitted


def _restore_and_scan(own: Ownership, published_ns: int) -> None:
    odometry = [_odom(9 * S, 0.9), _odom(10 * S, 1.0), _odom(11 * S, 1.1)]
    own.restore(_pose("r1", 10 * S + S // 2), odometry, published_ns)
    live = _odom(500 * S, 30.0)  # the robot's first reading after the restart
    assert own.offer("r1", "odom", encode(live), live, 1000 * S)


def test_a_fresh_restored_pose_seeds_an_initial_pose_anchored_at_its_stamp() -> None:
    own, admitted = _ownership(max_age_s=300)
    _restore_and_scan(own, published_ns=990 * S)  # 10 s old
    kinds = [(k, m.stamp_ns // (S // 10)) for _, k, m in admitted]
    # the reading at or before the stamp and the one after, the seed, then the live reading
    assert kinds == [("odom", 100), ("odom", 110), ("initialpose", 105), ("odom", 5000)]
    seed = admitted[2][2]
    assert isinstance(seed, InitialPose)
    assert (seed.map_id, seed.x, seed.y, seed.theta) == ("m1", 1.0, 2.0, 0.3)
    figures = own.figures()
    assert (figures["resumed"], figures["resumed_relocalize"]) == (1, 0)


def test_an_old_restored_pose_seeds_a_relocalization_on_its_map() -> None:
    own, admitted = _ownership(max_age_s=300)
    _restore_and_scan(own, published_ns=600 * S)  # 400 s old
    kinds = [k for _, k, _ in admitted]
    assert kinds == ["odom", "odom", "relocalize", "odom"]
    seed = admitted[2][2]
    assert isinstance(seed, Relocalize)
    assert (seed.map_id, seed.region) == ("m1", None)
    figures = own.figures()
    assert (figures["resumed"], figures["resumed_relocalize"]) == (1, 1)


def test_a_newer_pose_from_the_bus_wins_over_the_restored_one() -> None:
    own, admitted = _ownership(max_age_s=300)
    own.follow_pose("r1", encode(_pose("r1", 20 * S, x=4.0)), 1_000_000)
    _restore_and_scan(own, published_ns=600 * S)  # older than what the bus said: not used
    seed = admitted[-2][2]
    assert isinstance(seed, InitialPose) and seed.x == 4.0
    assert own.figures()["resumed"] == 0
