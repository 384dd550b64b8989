"""The audit's matching as a replay goes: the same verdict as matching the whole lists, in
memory that holds only the poses still waiting for their other half."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.logs.audit import audit, audit_match
from service.logs.posematch import PoseMatch, PoseRecord


def _pose(robot: str, stamp: int, x: float = 0.0, status: str = "tracking") -> PoseRecord:
    return PoseRecord(robot, stamp, "m1", x, 0.0, 0.0, status, f"{stamp},{x!r},{status}".encode())


_SIDE = st.lists(
    st.tuples(
        st.sampled_from(["r1", "r2"]),
        st.integers(0, 6),  # few stamps: equal stamps on a side, poses on one side only
        st.sampled_from([0.0, 0.5]),
        st.sampled_from(["tracking", "lost"]),
    ),
    max_size=25,
)


@settings(max_examples=200, deadline=None)
@given(recorded=_SIDE, recomputed=_SIDE, gap=st.none() | st.integers(0, 7), seed=st.integers())
def test_any_interleaving_gives_the_audit_of_the_whole_lists(
    recorded: list[tuple[str, int, float, str]],
    recomputed: list[tuple[str, int, float, str]],
    gap: int | None,
    seed: int,
) -> None:
    rec = [_pose(*p) for p in recorded]
    new = [_pose(*p) for p in recomputed]
    whole = audit(
        {r: [p for p in rec if p.robot == r] for r in ("r1", "r2")},
        {r: [p for p in new if p.robot == r] for r in ("r1", "r2")},
        gap,
    )
    # Fed as a replay meets them: the two sides interleaved at random, each in its order.
    match = PoseMatch(gap)
    rng = random.Random(seed)
    i = j = 0
    while i < len(rec) or j < len(new):
        if j == len(new) or (i < len(rec) and rng.random() < 0.5):
            match.recorded(rec[i])
            i += 1
        else:
            match.recomputed(new[j])
            j += 1
    streamed = [a for a in audit_match(match) if a.robot in {p.robot for p in rec + new}]
    whole = [a for a in whole if a.robot in {p.robot for p in rec + new}]
    assert len(streamed) == len(whole)
    for a, b in zip(streamed, whole, strict=True):
        assert (a.robot, a.matched, a.identical, a.missing, a.extra, a.unverified) == (
            b.robot, b.matched, b.identical, b.missing, b.extra, b.unverified
        )  # fmt: skip
        assert (a.status_differs, a.after_gap) == (b.status_differs, b.after_gap)
        assert (a.max_translation, a.max_heading) == (b.max_translation, b.max_heading)
        assert abs(a.rms_translation - b.rms_translation) <= 1e-12


def test_a_long_log_that_passes_holds_only_the_last_moment() -> None:
    """Each recorded pose comes a few scans after its recomputed one, as in a live log."""
    match = PoseMatch()
    lag = 3
    most = 0
    for k in range(100_000 + lag):
        if k < 100_000:
            match.recomputed(_pose("r1", k, 0.01 * k))
        if k >= lag:
            match.recorded(_pose("r1", k - lag, 0.01 * (k - lag)))
        most = max(most, match.waiting())
    (a,) = audit_match(match)
    assert (a.matched, a.identical, a.missing, a.extra) == (100_000, 100_000, 0, 0)
    assert most == lag and match.waiting() == 0


def test_poses_without_their_other_half_are_judged_at_the_end() -> None:
    match = PoseMatch()
    match.recomputed(_pose("r1", 1))
    match.recorded(_pose("r1", 2))
    match.recomputed(_pose("r1", 3))  # after the last recorded pose: unverified
    (a,) = audit_match(match)
    assert (a.matched, a.missing, a.extra, a.unverified) == (0, 1, 1, 1)
    assert not a.passed(1.0, 1.0)
    assert audit_match(PoseMatch()) == []  # nothing recorded: nothing to audit


def test_matches_of_other_robots_merge_and_of_the_same_robot_do_not() -> None:
    one, two = PoseMatch(), PoseMatch()
    one.recorded(_pose("r1", 1))
    one.recomputed(_pose("r1", 1))
    two.recorded(_pose("r2", 1))
    one.merge(two)
    assert [a.robot for a in audit_match(one)] == ["r1", "r2"]
    assert (one.recorded_total, one.recomputed_total) == (2, 1)
    with pytest.raises(ValueError, match="r1"):
        one.merge(one)
