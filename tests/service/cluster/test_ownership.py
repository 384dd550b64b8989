"""Membership from liveliness events, and one instance's ownership and handover seeding."""

from __future__ import annotations

import itertools
import time

import pytest
from scaleout_harness import wait_until

from schemas import (
    Hypothesis,
    InitialPose,
    LaserScan,
    Odometry,
    PoseEstimate,
    Relocalize,
    encode,
)
from service.cluster.membership import Membership, owner_of
from service.cluster.ownership import Ownership
from service.keys import InputKind, Message

ROBOTS = [f"robot-{i}" for i in range(100)]
LIMIT = 1_000_000


# ---------------------------------------------------------------------------- membership
def test_membership_follows_tokens_and_keeps_itself() -> None:
    changes: list[list[str]] = []
    m = Membership("i1", on_change=lambda: changes.append(m.members))
    assert m.members == ["i1"]
    assert all(m.owns(r) for r in ROBOTS)  # alone, it owns everything
    assert m.update("i2", alive=True)
    assert not m.update("i2", alive=True)
    assert not m.update("i1", alive=False)  # its own token's DELETE (at close) changes nothing
    assert m.members == ["i1", "i2"]
    assert [r for r in ROBOTS if m.owns(r)] == [
        r for r in ROBOTS if owner_of(r, ["i1", "i2"]) == "i1"
    ]
    # the priming get does not revive a member the subscriber saw leave
    assert m.update("i3", alive=True) and m.update("i3", alive=False)
    assert not m.update("i3", alive=True, prime=True)
    assert m.update("i4", alive=True, prime=True)
    assert not m.update("a/b", alive=True)
    assert changes == [["i1", "i2"], ["i1", "i2", "i3"], ["i1", "i2"], ["i1", "i2", "i4"]]


# ---------------------------------------------------------------------------- ownership
Admitted = list[tuple[str, InputKind, Message, int]]


def _odom(stamp: int, x: float = 0.0) -> tuple[bytes, Odometry]:
    msg = Odometry(stamp_ns=stamp, x=x, y=0.0, theta=0.0)
    return encode(msg), msg


def _pose(robot: str, stamp: int) -> PoseEstimate:
    return PoseEstimate(
        stamp_ns=stamp, robot_id=robot, map_id="m1", x=1.0, y=2.0, theta=0.3,
        status="tracking", discrepancy=0.01, iterations=1,
    )  # fmt: skip


def _ownership(
    m: Membership, fetch: object = None, released: list[str] | None = None
) -> tuple[Ownership, Admitted]:
    admitted: Admitted = []
    clock = itertools.count(1_000)
    own = Ownership(
        m,
        lambda robot, kind, payload, msg, received: admitted.append((robot, kind, msg, received)),
        lambda: next(clock),
        tail_ns=5_000_000_000,
        on_release=(released.append if released is not None else None),
    )
    own.ready = True
    if callable(fetch):
        own.start(fetch)
    return own, admitted


def _robot_of(owner: str, members: list[str]) -> str:
    return next(r for r in ROBOTS if owner_of(r, members) == owner)


def test_takeover_seeds_from_the_last_pose_with_the_odometry_tail() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    own, admitted = _ownership(m)
    robot = _robot_of("b", ["a", "b"])
    s = 1_000_000_000
    for i in range(1, 6):  # odometry while b owns it: ignored, kept in the tail
        payload, msg = _odom(i * s, x=float(i))
        assert not own.offer(robot, "odom", payload, msg, 10 + i)
        own.ignore(robot, "odom", payload, LIMIT)
    own.follow_pose(robot, encode(_pose(robot, int(3.5 * s))), LIMIT)
    own.follow_pose(robot, encode(_pose(robot, 2 * s)), LIMIT)  # older: not kept
    assert admitted == []
    m.update("b", alive=False)  # b dies: a owns everything
    payload, msg = _odom(6 * s, x=6.0)
    assert own.offer(robot, "odom", payload, msg, 20)
    kinds = [(k, m_.stamp_ns // 10**8) for _, k, m_, _ in admitted]
    # odometry from the reading at or before the pose's stamp on, the seed, then the input
    assert kinds == [("odom", 30), ("odom", 40), ("odom", 50), ("initialpose", 35), ("odom", 60)]
    seed = admitted[3][2]
    assert isinstance(seed, InitialPose)
    assert (seed.map_id, seed.x, seed.y, seed.theta) == ("m1", 1.0, 2.0, 0.3)
    received = [r for *_, r in admitted]
    assert received == sorted(received) and len(set(received)) == len(received)
    fig = own.figures()
    assert fig["owned"] == [robot] and fig["handover_seeds"] == 1
    assert fig["ignored_not_owner"] == 5 + 5  # offers refused and ignore() calls


def test_odometry_of_a_robot_owned_elsewhere_is_decoded_only_for_its_seed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from service.cluster import ownership

    decoded: list[type] = []
    real = ownership.decode

    def counting(model: type, payload: bytes, max_bytes: int = LIMIT) -> object:
        decoded.append(model)
        return real(model, payload, max_bytes=max_bytes)

    monkeypatch.setattr("service.cluster.ownership.decode", counting)
    m = Membership("a")
    m.update("b", alive=True)
    now = [0]
    admitted: Admitted = []
    own = Ownership(
        m,
        lambda robot, kind, payload, msg, received: admitted.append((robot, kind, msg, received)),
        lambda: now[0],
        tail_ns=1_000,
    )
    own.ready = True
    robot = _robot_of("b", ["a", "b"])
    for at, payload in (
        (200, _odom(2_900)[0]),  # received longer than tail_ns before the last: trimmed
        (600, b'{"stamp_ns": 3000, "x": '),  # undecodable: its owner reports it, left out
        (1_500, _odom(3_100)[0]),
    ):
        now[0] = at
        own.ignore(robot, "odom", payload, LIMIT)
    assert decoded == []  # kept as they came
    own.follow_pose(robot, encode(_pose(robot, 3_050)), LIMIT)
    m.update("b", alive=False)
    now[0] = 1_600
    payload, msg = _odom(3_200)
    assert own.offer(robot, "odom", payload, msg, 20)
    kinds = [(k, m_.stamp_ns) for _, k, m_, _ in admitted]
    assert kinds == [("odom", 3_100), ("initialpose", 3_050), ("odom", 3_200)]
    assert decoded.count(Odometry) == 2  # the two readings left in the tail, at the seed


def test_a_robot_taken_over_while_ambiguous_is_relocalized_again() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    own, admitted = _ownership(m)
    robot = _robot_of("b", ["a", "b"])
    guesses = (
        Hypothesis(x=1.0, y=2.0, theta=0.3, score=0.9),
        Hypothesis(x=9, y=2, theta=3, score=0.9),
    )
    ambiguous = _pose(robot, 3_000).model_copy(update={"status": "lost", "hypotheses": guesses})
    own.follow_pose(robot, encode(ambiguous), LIMIT)
    m.update("b", alive=False)
    payload, msg = _odom(4_000)
    own.offer(robot, "odom", payload, msg, 10)
    # Not seeded at the best guess (which may be the wrong place): relocalized on its map.
    assert [k for _, k, _, _ in admitted] == ["relocalize", "odom"]
    assert admitted[0][2] == Relocalize(stamp_ns=3_000, map_id="m1")


def test_an_initial_pose_its_dead_owner_never_used_is_replayed_on_takeover() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    own, admitted = _ownership(m)
    robot = _robot_of("b", ["a", "b"])
    own.follow_pose(robot, encode(_pose(robot, 3_000)), LIMIT)
    placed = InitialPose(stamp_ns=4_000, map_id="m2", x=5.0, y=6.0, theta=0.0)
    own.ignore(robot, "initialpose", encode(placed), LIMIT)
    payload, msg = _odom(3_500)
    own.ignore(robot, "odom", payload, LIMIT)
    m.update("b", alive=False)
    payload, msg = _odom(4_500)
    own.offer(robot, "odom", payload, msg, 10)
    assert [(k, m_.stamp_ns) for _, k, m_, _ in admitted] == [
        ("odom", 3_500),
        ("initialpose", 4_000),
        ("odom", 4_500),
    ]
    assert admitted[1][2] == placed


def test_unknown_pose_is_fetched_while_inputs_wait() -> None:
    asked: list[str] = []
    robot = "rx"

    def fetch(r: str) -> PoseEstimate | None:
        asked.append(r)
        time.sleep(0.1)
        return _pose(r, 500)

    own, admitted = _ownership(Membership("a"), fetch)
    try:
        for i in range(3):
            payload, msg = _odom(1_000 + i)
            own.offer(robot, "odom", payload, msg, 1 + i)
        assert admitted == []  # held while the get runs
        assert wait_until(lambda: len(admitted) == 4, 3.0)
    finally:
        own.close()
    assert asked == [robot]
    # the odometry held goes before the seed, as a tail does (none is at or before its stamp)
    assert [k for _, k, _, _ in admitted] == ["odom", "odom", "odom", "initialpose"]
    assert [m.stamp_ns for _, _, m, _ in admitted] == [1_000, 1_001, 1_002, 500]
    assert own.figures()["handover_fetched"] == 1


def test_no_pose_anywhere_releases_inputs_unseeded_and_an_initial_pose_needs_no_fetch() -> None:
    asked: list[str] = []
    own, admitted = _ownership(Membership("a"), asked.append)
    try:
        payload, msg = _odom(7)
        own.offer("new", "odom", payload, msg, 1)
        assert wait_until(lambda: len(admitted) == 1, 3.0)
        ip = InitialPose(stamp_ns=9, map_id="m1", x=0.0, y=0.0, theta=0.0)
        own.offer("placed", "initialpose", encode(ip), ip, 2)
    finally:
        own.close()
    assert asked == ["new"]
    assert [(r, k) for r, k, _, _ in admitted] == [("new", "odom"), ("placed", "initialpose")]
    assert own.figures()["handover_seeds"] == 0


def test_an_initial_pose_does_not_wait_behind_the_lookups_of_other_new_ids() -> None:
    """Each new id's pose is looked up on the bus on one thread, in turn: a flood of made-up
    ids held a robot an operator placed behind all of theirs. Its InitialPose now places it at
    once, and a robot no longer waiting is not looked up."""
    asked: list[str] = []

    def fetch(r: str) -> PoseEstimate | None:
        asked.append(r)
        time.sleep(0.05)
        return None

    own, admitted = _ownership(Membership("a"), fetch)
    try:
        for i in range(40):  # 2 s of lookups
            payload, msg = _odom(100 + i)
            own.offer(f"fake{i}", "odom", payload, msg, 1 + i)
        payload, msg = _odom(200)
        own.offer("real", "odom", payload, msg, 100)
        ip = InitialPose(stamp_ns=201, map_id="m1", x=0.0, y=0.0, theta=0.0)
        own.offer("real", "initialpose", encode(ip), ip, 101)
        real = [(k, m.stamp_ns) for r, k, m, _ in admitted if r == "real"]
        assert real == [("odom", 200), ("initialpose", 201)], real  # at once, in order
        assert own.active("real")
        assert wait_until(lambda: len(admitted) == 42, 5.0)
    finally:
        own.close()
    assert "real" not in asked and len(asked) == 40


def _scan(stamp: int) -> tuple[bytes, LaserScan]:
    msg = LaserScan(
        stamp_ns=stamp, angle_min=0.0, angle_increment=0.1, range_min=0.1, range_max=10.0,
        ranges=(1.0, 2.0),
    )  # fmt: skip
    return encode(msg), msg


def test_a_joiner_waits_for_the_previous_owners_last_answers_and_answers_no_scan_twice() -> None:
    """The joiner owns the robot at once, but its previous owner still answers the scans it took
    before the token reached it: held through the grace, seeded from the newest pose then, the
    scans that pose answers are not localized again."""
    asked: list[str] = []
    m = Membership("a")
    m.update("b", alive=True)
    robot = _robot_of("a", ["a", "b"])
    own, admitted = _ownership(m, asked.append)
    ms = 1_000_000
    own.follow_pose(robot, encode(_pose(robot, 1_000 * ms)), LIMIT)  # b's answer before the join
    own.grace_until = time.monotonic() + 0.3
    try:
        for kind, (payload, msg) in [
            ("odom", _odom(1_050 * ms, x=1.0)),
            ("scan", _scan(1_100 * ms)),
            ("odom", _odom(1_150 * ms, x=2.0)),
            ("scan", _scan(1_200 * ms)),
        ]:
            assert own.offer(robot, kind, payload, msg, 10)
        assert admitted == [] and own.acquiring() == 1  # held through the grace
        own.follow_pose(robot, encode(_pose(robot, 1_100 * ms)), LIMIT)  # b answered 1.1 s
        assert wait_until(lambda: len(admitted) == 4, 3.0)
    finally:
        own.close()
    assert asked == []  # its pose was followed: nothing to fetch
    kinds = [(k, m_.stamp_ns // ms) for _, k, m_, _ in admitted]
    # the odometry from the reading at or before the seed on, the seed at b's last answer, and
    # only the scan b did not answer
    assert kinds == [("odom", 1_050), ("odom", 1_150), ("initialpose", 1_100), ("scan", 1_200)]
    assert own.figures()["handover_answered_elsewhere"] == 1


def test_a_scan_no_newer_than_the_robots_last_pose_is_not_localized_again() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    robot = _robot_of("b", ["a", "b"])
    own, admitted = _ownership(m)
    own.follow_pose(robot, encode(_pose(robot, 2_000)), LIMIT)
    m.update("b", alive=False)
    for stamp in (2_000, 2_100):
        payload, msg = _scan(stamp)
        assert own.offer(robot, "scan", payload, msg, stamp)
    assert [(k, m_.stamp_ns) for _, k, m_, _ in admitted] == [
        ("initialpose", 2_000),
        ("scan", 2_100),
    ]
    assert own.figures()["handover_answered_elsewhere"] == 1


def test_a_joining_member_takes_its_robots_away() -> None:
    released: list[str] = []
    m = Membership("a")
    own, _ = _ownership(m, released=released)
    robot = _robot_of("b", ["a", "b"])
    keep = _robot_of("a", ["a", "b"])
    for r in (robot, keep):
        ip = InitialPose(stamp_ns=9, map_id="m1", x=0.0, y=0.0, theta=0.0)
        assert own.offer(r, "initialpose", encode(ip), ip, 2)
    assert own.owned() == sorted([robot, keep])
    m.update("b", alive=True)
    assert released == [robot]
    assert own.owned() == [keep] and own.active(keep) and not own.active(robot)
    payload, msg = _odom(10)
    assert not own.offer(robot, "odom", payload, msg, 3)


def test_own_poses_are_kept_undecoded_and_seed_as_followed_ones_do() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    own, admitted = _ownership(m)
    robot, other = _robot_of("b", ["a", "b"]), ROBOTS[-1]
    newer = _pose(robot, 5_000).model_copy(update={"x": 7.0})
    own.follow_own_pose(robot, encode(_pose(robot, 3_000)), 3_000)
    own.follow_pose(robot, encode(_pose(robot, 2_000)), LIMIT)  # older than the own one
    assert own.last_pose(robot) == _pose(robot, 3_000)
    own.follow_own_pose(robot, encode(newer), 5_000)
    own.follow_own_pose(robot, encode(_pose(robot, 4_000)), 4_000)  # older: not kept
    own.remember(_pose(robot, 4_500))  # older than the own one: not kept either
    own.follow_own_pose(other, encode(_pose(other, 1_000)), 1_000)
    own.follow_pose(other, encode(_pose(other, 1_500)), LIMIT)  # newer, from the bus
    assert own.last_pose(other) == _pose(other, 1_500)
    m.update("b", alive=False)
    payload, msg = _odom(6_000)
    own.offer(robot, "odom", payload, msg, 10)
    assert [(k, m_.stamp_ns) for _, k, m_, _ in admitted] == [
        ("initialpose", 5_000),
        ("odom", 6_000),
    ]
    seed = admitted[0][2]
    assert isinstance(seed, InitialPose) and (seed.x, seed.y, seed.theta) == (7.0, 2.0, 0.3)
    assert own.last_pose(robot) == newer


def test_own_poses_count_against_the_robot_bound_and_the_stamp_bound() -> None:
    own, _ = _ownership(Membership("a"))
    own.followed.max_robots = 2
    own.followed.max_ahead_ns = 1_000_000  # the test clock counts from 1,000
    own.follow_own_pose("r1", encode(_pose("r1", 10)), 10)
    own.follow_pose("r2", encode(_pose("r2", 10)), LIMIT)
    own.follow_own_pose("r3", encode(_pose("r3", 10)), 10)  # two robots held already
    assert own.last_pose("r3") is None and own.last_pose("r1") == _pose("r1", 10)
    own.follow_own_pose("r2", encode(_pose("r2", 20)), 20)  # a robot held: kept
    assert own.last_pose("r2") == _pose("r2", 20)
    ahead = 10**12
    own.follow_own_pose("r1", encode(_pose("r1", ahead)), ahead)
    assert own.last_pose("r1") == _pose("r1", 10) and own.figures()["poses_rejected"] == 1
    own.forget("r2")
    assert own.last_pose("r2") is None


def test_inputs_held_for_a_seed_are_bounded_in_bytes_over_every_robot(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from service.cluster import ownership

    payload, msg = _odom(1_000)
    monkeypatch.setattr(ownership, "HOLD_BYTES", 3 * len(payload))
    stay, late = [r for r in ROBOTS if owner_of(r, ["a", "b"]) == "a"][:2]
    go = _robot_of("b", ["a", "b"])
    m = Membership("a")
    own, admitted = _ownership(m)  # no fetching thread: the held inputs stay held
    for robot in (go, go, stay):  # three inputs held: the bytes held are full
        assert own.offer(robot, "odom", payload, msg, 1)
    assert own.offer(stay, "odom", payload, msg, 2)  # over: dropped, counted
    assert own.offer(late, "odom", payload, msg, 3)  # over: not acquired yet, counted
    assert own.acquiring() == 2 and not own.holds(late)
    assert own.figures()["handover_held_dropped"] == 2
    m.update("b", alive=True)  # go moves away: its two held inputs are freed
    assert not own.holds(go)
    assert own.offer(late, "odom", payload, msg, 4) and own.holds(late)
    assert own.offer(stay, "odom", payload, msg, 5)
    assert own.acquiring() == 2 and own.figures()["handover_held_dropped"] == 2
    assert admitted == []
