"""The fleet benchmark's verdicts: held (the whole run) and issue 21's target (after the start)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from bench.fleet import main as fleet_main
from bench.fleet import share_floor, speed_line, verdicts
from bench.fleetrun import scans_recorded
from service.logs.mcaplog import McapRecorder


def _row(**changed: Any) -> dict[str, Any]:
    row = {"sent": 40000, "dropped": 100, "uncounted": 0, "p99": 30.0, "answered_after": 1.0}
    row.update(changed)
    return row


def test_a_size_that_drops_its_start_is_not_held_but_meets_the_target() -> None:
    # Every robot's first scan searches wide at once: 2.6 % dropped, none after the first 2 s.
    assert verdicts(_row(dropped=1041)) == (False, True)


def test_the_target_asks_for_99_percent_answered_after_the_start() -> None:
    assert verdicts(_row(answered_after=0.99)) == (True, True)
    assert verdicts(_row(answered_after=0.989)) == (True, False)


def test_a_slow_p99_or_an_uncounted_scan_fails_both() -> None:
    assert verdicts(_row(p99=50.1)) == (False, False)
    assert verdicts(_row(uncounted=1)) == (False, False)


def test_the_scans_a_service_recorded_are_counted_over_its_processes_files(
    tmp_path: Path,
) -> None:
    # Two processes' logs, as a host's: scans, odometry and poses; only the scans count.
    t0 = 1_000_000_000
    for instance, robots in (("bench-p0", ("r1", "r2")), ("bench-p1", ("r3",))):
        rec = McapRecorder(tmp_path, instance=instance, chunk_size=4096)
        for step in range(5):
            for robot in robots:
                stamp = t0 + step * 100_000_000
                rec.record(f"rlutf/robots/{robot}/odom", "rlutf.Odometry", b"{}", stamp, stamp)
                rec.record(f"rlutf/robots/{robot}/scan", "rlutf.LaserScan", b"{}", stamp, stamp)
                rec.record(f"rlutf/robots/{robot}/pose", "rlutf.PoseEstimate", b"{}", stamp, stamp)
        rec.close()
    assert len(list(tmp_path.glob("*.mcap"))) == 2
    assert scans_recorded(tmp_path) == 3 * 5


def test_the_share_floor_counts_zenohs_threads_against_the_update() -> None:
    # Run 12's kind of table: the update 0.3 ms a scan, Zenoh's threads 0.1, the rest 0.2.
    by_thread = {
        "host": {"rlutf-inputs": 0.30, "rx-*": 0.04, "tx-*": 0.02, "rlutf-recorder": 0.02},
        "processes": {"rlutf-inputs": 0.18, "rx-*": 0.03, "app-*": 0.01},
    }
    said = share_floor(by_thread, update_ms=0.30)
    assert "Zenoh's threads (acc-*, app-*, net-*, rx-*, tx-*) 0.100 ms" in said
    assert "everything else of the service's" in said and "0.200 ms" in said
    assert said.endswith("would be 25 % (the bus's threads over theirs and the update's).")


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--robots", "0"], "at least 1"),
        (["--robots", "50,x"], "whole numbers"),
        (["--duration", "nan"], "must be over 0"),
    ],
)
def test_sizes_and_durations_it_cannot_run_are_refused_before_a_service_starts(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as ended:
        fleet_main(argv)
    assert ended.value.code == 2
    assert says in capsys.readouterr().err


def test_the_service_is_read_against_the_localizer_alone_timed_before_each_size() -> None:
    line = speed_line([(100, 0.2, 0.7), (200, 0.25, 0.6)])
    assert "100 robots 0.200 ms (the service's CPU per scan sent 3.5 times it)" in line
    assert "200 robots 0.250 ms (the service's CPU per scan sent 2.4 times it)" in line
    assert "nan times it" in speed_line([(10, 0.0, 0.5)])  # too short to time: no ratio
