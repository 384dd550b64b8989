"""bench.failover's reading of a run: which robots lost their poses at the kill, how long until
their next one, the gaps after, how far off the first pose after a gap is, and poses twice."""

from __future__ import annotations

import math
import os

from bench.failover import children, figures

S = 1_000_000_000
MS = 1_000_000


def _every_100ms(
    robot: str, start: int, end: int, off: float = 0.001
) -> list[tuple[str, int, int, float]]:
    """Poses of ``robot`` arriving every 0.1 s over ``[start, end)``, stamped when they came."""
    return [(robot, t, t, off) for t in range(start, end, 100 * MS)]


def test_a_robot_that_lost_its_owner_counts_from_the_kill_to_its_next_pose() -> None:
    killed = 10 * S
    stamped = [
        *_every_100ms("steady", 9 * S, 14 * S),  # owned by the survivor: no gap
        # owned by the killed process: last pose just before the kill, the next 0.8 s after it,
        # 3 cm off; then a second gap of 1.2 s when it returns to the restarted process
        *_every_100ms("moved", 9 * S, killed - 50 * MS),
        ("moved", killed + 800 * MS, killed + 800 * MS, 0.03),
        ("moved", killed + 900 * MS, killed + 900 * MS, 0.001),
        ("moved", killed + 2100 * MS, killed + 2100 * MS, 0.07),
        # a slow robot whose gap across the kill is under the threshold: not moved
        ("quick", killed - 200 * MS, killed - 200 * MS, 0.001),
        ("quick", killed + 200 * MS, killed + 200 * MS, 0.001),
    ]
    f = figures({"ids": ["steady", "moved", "quick"], "stamped": stamped, "killed": killed})
    assert f["moved_count"] == 1 and f["within_2s"] == 1
    assert math.isclose(float(f["moved"][0]), 0.8)
    assert math.isclose(f["across"], 0.9)  # "moved": its pose at 9.9 s to the one at 10.8 s
    assert f["later_count"] == 1 and math.isclose(float(f["later"][0]), 1.2)
    assert sorted(round(float(x), 3) for x in f["off_cm"]) == [3.0, 7.0]
    assert f["within_5cm"] == 1 and f["gaps"] == 2
    assert f["twice"] == 0 and f["poses"] == len(stamped)


def test_a_scan_answered_by_two_owners_is_counted_once_per_scan() -> None:
    stamped = [("r0", 1 * S, 5, 0.0), ("r0", 1 * S + 1, 5, 0.0), ("r0", 2 * S, 6, 0.0)]
    f = figures({"ids": ["r0"], "stamped": stamped, "killed": 0})  # the kill before them all
    assert f["twice"] == 1
    assert f["moved_count"] == 0 and math.isnan(float(f["moved"][0]))
    assert math.isnan(f["across"])  # no pose before the kill
    assert f["later_count"] == 1  # the second between its last two poses


def test_a_robot_never_served_after_the_kill_is_moved_and_late() -> None:
    killed = 10 * S
    stamped = [*_every_100ms("lost", 9 * S, killed), *_every_100ms("fine", 9 * S, 12 * S)]
    f = figures({"ids": ["lost", "fine", "silent"], "stamped": stamped, "killed": killed})
    assert f["moved_count"] == 2  # "lost" stopped at the kill; "silent" never had a pose
    assert f["within_2s"] == 0 and all(math.isinf(float(x)) for x in f["moved"])


def test_children_are_read_from_proc() -> None:
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert child.pid in children(os.getpid())
    finally:
        child.kill()
        child.wait()
