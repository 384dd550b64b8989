"""What the command line shows a person: tables, units, ages, Events, and the lost wording."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from rlutf.localizer import LocalizeResult
from schemas import Event, PoseEstimate, RobotState, WaitingRobot
from service.cli.present import (
    age,
    event_line,
    health_table,
    pose_line,
    poses_table,
    robots_table,
)
from service.relocalization import unfit as _unfit


def _state(robot: str, age_s: float | None, owner: str, x: float = 0.0) -> RobotState:
    return RobotState(
        robot_id=robot,
        map_id="m",
        status="tracking",
        x=x,
        y=-1.5,
        theta=math.pi / 2,
        age_s=age_s,
        latency_ms=None if age_s is None else 2.25,
        owner=owner,
        sigma_xy_m=None if age_s is None else 0.0123,
        sigma_theta_rad=None if age_s is None else math.radians(0.5),
    )


def test_robots_table_in_degrees_and_centimetres_with_silent_and_waiting_robots() -> None:
    waiting = WaitingRobot(robot_id="r0", reason="not_initialized", age_s=0.5, owner="a")
    text = robots_table(
        [
            _state("r1", 0.123, "a", x=12.3456),
            _state("robot-22", None, "b"),
            _state("r3", 107, "a"),
        ],
        [waiting],
    )
    header, first, second, third, fourth, blank, hint = text.splitlines()
    assert header.split() == [
        "robot",
        "map",
        "status",
        "x",
        "m",
        "y",
        "m",
        "θ",
        "°",
        "±xy",
        "cm",
        "±θ",
        "°",
        "age",
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
        "90.0",
        "1.2",
        "0.50",
        "0.12",
        "s",
        "2.2",
        "a",
    ]
    assert second.split() == [
        "robot-22",
        "m",
        "tracking",
        "0.000",
        "-1.500",
        "90.0",
        "-",
        "-",
        "-",
        "-",
        "b",
    ]
    assert third.split()[:4] == ["r3", "m", "silent", "(tracking)"]
    assert "1 min 47 s" in third
    assert fourth.split()[:3] == ["r0", "-", "waiting"]
    assert len({line.index("-1.500") for line in (first, second, third)}) == 1  # aligned
    assert blank == "" and "rlutf initialpose ROBOT --map ID --pose X,Y,THETA" in hint


def test_a_robot_with_an_initial_pose_and_no_scan_reads_no_scan_yet() -> None:
    waiting = WaitingRobot(robot_id="r5", reason="no_scan_yet", age_s=3.0, owner="a")
    text, hint = robots_table([_state("r1", 0.1, "a")], [waiting]).split("\n\n")
    assert text.splitlines()[-1].split()[:5] == ["r5", "-", "no", "scan", "yet"]
    assert hint.startswith("no scan yet:") and "rlutf events ROBOT" in hint
    # with a robot waiting for an initial pose too: both hints
    other = WaitingRobot(robot_id="r6", reason="not_initialized", age_s=1.0, owner="a")
    _, first, second = robots_table([], [waiting, other]).split("\n\n")
    assert "rlutf initialpose" in first and second.startswith("no scan yet:")


def test_a_robot_whose_map_is_missing_reads_no_map_with_its_map_and_what_to_do() -> None:
    # An initial pose on a map no storage has: the robot sent no scan, so the hint for robots
    # that send scans without a pose would be wrong; the map it waits for is shown.
    missing = WaitingRobot(
        robot_id="r4", reason="map_not_found", age_s=1.0, owner="a", map_id="dpeot"
    )
    placed = WaitingRobot(robot_id="r5", reason="no_scan_yet", age_s=3.0, owner="a", map_id="m")
    text, first, second = robots_table([], [placed, missing]).split("\n\n")
    rows = [line.split() for line in text.splitlines()[1:]]
    assert [r[:3] for r in rows] == [["r5", "m", "no"], ["r4", "dpeot", "no"]]
    assert rows[1][3] == "map"
    assert first.startswith("no map:") and "rlutf map list" in first
    assert "sends scans" not in first + second and second.startswith("no scan yet:")


def test_a_table_without_waiting_robots_has_no_hint() -> None:
    assert "initialpose" not in robots_table([_state("r1", 0.1, "a")])


@pytest.mark.parametrize(
    ("seconds", "text"),
    [(None, "-"), (0.04, "0.04 s"), (12.4, "12 s"), (107, "1 min 47 s"), (7500, "2 h 05 min")],
)
def test_ages_read_as_seconds_minutes_hours(seconds: float | None, text: str) -> None:
    assert age(seconds) == text


def _pose() -> PoseEstimate:
    return PoseEstimate(
        stamp_ns=1_000_000_000,
        robot_id="r1",
        map_id="m1",
        x=1.0,
        y=-2.0,
        theta=-math.pi / 2,
        status="corrected",
        discrepancy=0.0123,
        iterations=2,
        covariance=[0.0004, 0, 0, 0, 0.0001, 0, 0, 0, math.radians(1) ** 2],
    )


def test_poses_in_degrees_centimetres_and_their_age() -> None:
    header, line = poses_table([_pose()], now_ns=3_500_000_000).splitlines()
    assert header.split()[-1] == "discrepancy"
    assert line.split() == [
        "r1",
        "m1",
        "corrected",
        "1.000",
        "-2.000",
        "-90.0",
        "2.0",
        "1.00",
        "2.50",
        "s",
        "0.0123",
    ]
    assert pose_line(_pose()) == (
        "r1 on m1: corrected at x 1.000 m, y -2.000 m, θ -90.0° ± 2.0 cm, 1.00°"
    )


def test_an_event_is_one_line_with_its_robot() -> None:
    ev = Event(
        stamp_ns=1_732_300_000_123_456_789,
        level="warning",
        code="not_initialized",
        key="rlutf/robots/r1/scan",
        message="scan before an initial pose",
    )
    line = event_line("r1", ev)
    assert line.endswith("warning  r1  not_initialized: scan before an initial pose")
    assert line[8:12] == ".123"
    assert "  -  not_initialized (rlutf/robots/r1/scan): scan" in event_line(None, ev)


def test_control_characters_from_the_bus_do_not_reach_the_terminal(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Any client may put a key, and an Event on {prefix}/events, with escape sequences in them:
    # printed raw they clear or recolour the operator's terminal.
    ev = Event(
        stamp_ns=1_732_300_000_123_456_789,
        level="error",
        code="invalid_key\x1b[31m",
        key="rlutf/robots/\x1b[2J\x1b[31mEVIL/scan",
        message="bad\x07 \x9b1m id é",
    )
    line = event_line(None, ev)
    assert "\x1b" not in line and "\x07" not in line and "\x9b" not in line
    assert "rlutf/robots/\\x1b[2J\\x1b[31mEVIL/scan" in line and "bad\\x07 \\x9b1m id é" in line
    from service.cli.query import show_other

    show_other()("rlutf/robots/\x1b[2J/events", 3, "junk\r")
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\r" not in err and "\\x1b[2J" in err


def _lost(fit: float, needed: float) -> LocalizeResult:
    return LocalizeResult(np.zeros(3), 0.5, 3, "lost", 10, fit=fit, fit_needed=needed)


def test_the_lost_wording_never_reads_as_a_contradiction() -> None:
    # the robot's usual share sets the bar: 92 % is under it, though over min_fit
    text = _unfit(_lost(0.92, 0.95), 0.1, 0.5)
    assert "only 92 % of its returns lie within 0.1 m" in text
    assert "under the 95 % needed" in text and "usually" in text
    assert "never under 50 %" in text
    # the shares are given with as many digits as it takes to tell them apart
    assert "only 92.1 %" in _unfit(_lost(0.921, 0.924), 0.1, 0.5)
    assert "under the 92.4 % needed" in _unfit(_lost(0.921, 0.924), 0.1, 0.5)
    # the plain floor
    text = _unfit(_lost(0.3, 0.5), 0.1, 0.5)
    assert text.startswith("the scan does not fit the map: only 30 %")
    assert "under the 50 % needed" in text
    # a result that does not say what was needed: min_fit
    assert "under the 50 % needed" in _unfit(_lost(0.3, math.nan), 0.1, 0.5)


def _health(instance: str, received: int = 1, **extra: object) -> Any:
    from schemas import Health

    return Health(
        instance=instance,
        stamp_ns=1,
        uptime_s=5.0,
        robots=1,
        received=received,
        rejected=0,
        processed=received,
        dropped=0,
        ready=True,
        extra=extra,
    )


def test_a_hosts_health_row_says_it_adds_its_processes_up() -> None:
    health = _health
    processes = [{"name": "h-p0"}, {"name": "h-p1"}]
    rows = health_table(
        [health("h", 30, host=True, processes=processes), health("h-p0", 10), health("h-p1", 20)]
    ).splitlines()[1:]
    assert [r.split()[0] for r in rows] == ["h", "h-p0", "h-p1"]
    assert "(host: 2 processes added up; latency: the slowest)" in rows[0]
    assert "host" not in rows[1] + rows[2]


def test_health_warns_of_an_instance_losing_its_log_or_its_pose_state() -> None:
    from service.cli.present import health_problems

    health = _health
    fine = {"recorder_unrecorded": 0, "recorder_overflow": 0, "state_write_errors": 0}
    lines = health_problems(
        [
            health("h", host=True, recorder_unrecorded=2000),  # its processes say it
            health("h-p0", **{**fine, "recorder_unrecorded": 1652}),
            health("h-p1", **{**fine, "state_write_errors": 3, "recorder_overflow": 7}),
            health("other", **fine),
            # failed writes before, written since: nothing to warn of now
            health("healed", **{**fine, "state_write_errors": 5, "state_write_failing": False}),
            health("old"),  # an instance that reports none of these figures
        ]
    )
    assert lines[0].startswith("h-p0: 1,652 messages not recorded: the log folder could not")
    assert [line.split(":")[0] for line in lines] == ["h-p0", "h-p1", "h-p1"]
    assert "recorder's queue was full" in lines[1] and "7" in lines[1]
    assert "a restart may not resume its robots" in lines[2]
    failing = health("f", **{**fine, "state_write_errors": 5, "state_write_failing": True})
    assert health_problems([failing])[0].startswith("f: 5 pose-state writes failed")


def test_payloads_that_are_not_events_are_said_at_most_every_few_seconds(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from service.cli.query import OTHER_EVERY_S, show_other

    t = [100.0]
    show = show_other(lambda: t[0])
    for _ in range(3):
        show("rlutf/events", 7, "invalid JSON")
    t[0] += OTHER_EVERY_S
    show("rlutf/robots/r1/events", 9, "x" * 400)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "rlutf events: rlutf/events: not an Event (7 bytes: invalid JSON)"
    assert lines[1].endswith("...) (and 2 more since the last such line)") and len(lines) == 2
    assert len(lines[1]) < 280


def test_payloads_that_are_not_events_from_several_threads_are_one_line_a_period(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Zenoh calls the callback from several threads: one line a period, every other counted."""
    import threading

    from service.cli.query import OTHER_EVERY_S, show_other

    t = [100.0]
    show = show_other(lambda: t[0])
    start = threading.Barrier(8)

    def burst() -> None:
        start.wait()
        for _ in range(500):
            show("rlutf/events", 7, "invalid JSON")

    threads = [threading.Thread(target=burst) for _ in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    t[0] += OTHER_EVERY_S
    show("rlutf/events", 7, "invalid JSON")
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2, lines
    assert lines[1].endswith("(and 3999 more since the last such line)"), lines


def test_a_robot_whose_scans_have_no_returns_reads_no_returns_with_its_hint() -> None:
    # A blocked lidar: the status read "no returns" but no line under the table said what it
    # means (every other waiting status has one).
    blocked = WaitingRobot(robot_id="r3", reason="no_returns", age_s=1.0, owner="a", map_id="m")
    text, hint = robots_table([], [blocked]).split("\n\n")
    assert text.splitlines()[-1].split()[:4] == ["r3", "m", "no", "returns"]
    assert hint.startswith("no returns:") and "lidar" in hint


def test_a_robot_whose_clock_is_ahead_reads_clock_ahead_with_its_hint() -> None:
    ahead = WaitingRobot(robot_id="r4", reason="stamp_rejected", age_s=1.0, owner="a", map_id="m")
    text, hint = robots_table([], [ahead]).split("\n\n")
    assert text.splitlines()[-1].split()[:4] == ["r4", "m", "clock", "ahead"]
    assert hint.startswith("clock ahead:") and "NTP" in hint


def test_a_robot_with_a_pose_whose_inputs_are_refused_reads_clock_ahead() -> None:
    base = {"robot_id": "r5", "map_id": "m", "status": "tracking", "x": 1.0, "y": 2.0}
    refused = RobotState(**base, theta=0.0, age_s=30.0, owner="a", refused="stamp_rejected")
    text, hint = robots_table([refused]).split("\n\n")
    assert text.splitlines()[-1].split()[2:5] == ["clock", "ahead", "(tracking)"]
    assert hint.startswith("clock ahead:")
