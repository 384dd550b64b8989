"""The audit's matching rules and verdicts, on poses made up for the purpose."""

from __future__ import annotations

import math

from rich.console import Console

from service.logs.audit import all_passed, audit, render
from service.logs.posematch import PoseRecord


def _pose(stamp: int, x: float = 0.0, theta: float = 0.0, status: str = "tracking") -> PoseRecord:
    payload = f"{stamp},{x!r},{theta!r},{status}".encode()
    return PoseRecord("r1", stamp, "m1", x, 0.0, theta, status, payload)


def test_identical_poses_pass_with_zero_deviation() -> None:
    poses = [_pose(i, 0.1 * i) for i in range(5)]
    (a,) = audit({"r1": poses}, {"r1": list(poses)})
    assert (a.matched, a.identical, a.missing, a.extra, a.unverified) == (5, 5, 0, 0, 0)
    assert a.max_translation == a.max_heading == 0.0
    assert all_passed([a], 1e-9, 1e-9)


def test_deviations_are_measured_and_judged_against_the_tolerance() -> None:
    recorded = [_pose(0), _pose(1, 1.0, math.pi - 0.01), _pose(2)]
    recomputed = [_pose(0), _pose(1, 1.003, -math.pi + 0.01), _pose(2)]
    (a,) = audit({"r1": recorded}, {"r1": recomputed})
    assert math.isclose(a.max_translation, 0.003, rel_tol=1e-9)
    assert math.isclose(a.max_heading, 0.02, rel_tol=1e-6)  # wrapped across +-pi
    assert math.isclose(a.rms_translation, 0.003 / math.sqrt(3), rel_tol=1e-9)
    assert a.identical == 2
    assert not a.passed(1e-9, 1e-9)
    assert not a.passed(0.01, 0.01 - 1e-6)
    assert a.passed(0.01, 0.03)


def test_missing_extra_unverified_and_status() -> None:
    recorded = [_pose(0), _pose(1), _pose(3)]
    recomputed = [_pose(0), _pose(2), _pose(3), _pose(4), _pose(5)]
    (a,) = audit({"r1": recorded}, {"r1": recomputed})
    assert (a.matched, a.missing, a.extra, a.unverified) == (2, 1, 1, 2)
    assert not a.passed(1.0, 1.0)
    tail_only = audit({"r1": recorded[:1]}, {"r1": recomputed[:1] + recomputed[3:]})[0]
    assert tail_only.unverified == 2 and tail_only.passed(1e-9, 1e-9)
    assert not tail_only.passed(1e-9, 1e-9, strict=True)
    (s,) = audit({"r1": [_pose(0)]}, {"r1": [_pose(0, status="lost")]})
    assert s.status_differs == 1 and not s.passed(1.0, 1.0)


def test_nothing_recorded_means_nothing_to_audit_and_table_renders() -> None:
    assert audit({}, {"r1": [_pose(0)]}) == []
    console = Console(record=True, width=160)
    audits = audit({"r1": [_pose(0)], "r2": []}, {"r1": [_pose(0, 1.0)], "r2": [_pose(1)]})
    render(audits, 1e-9, 1e-9, console)
    text = console.export_text()
    assert "FAIL" in text and "r2" in text and "ok" in text
