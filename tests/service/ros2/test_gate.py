"""The odometry gate: a scan follows the odometry at its stamp, whatever the arrival order."""

from __future__ import annotations

import itertools

from schemas import InitialPose, LaserScan, Odometry
from service.ros2.gate import OdometryGate


def _scan(stamp: int) -> LaserScan:
    return LaserScan(
        stamp_ns=stamp,
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.0,
        range_max=5.0,
        ranges=[1.0],
    )


def _odom(stamp: int) -> Odometry:
    return Odometry(stamp_ns=stamp, x=0.0, y=0.0, theta=0.0)


class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        self.now += 1
        return self.now


def _gate(wait_ns: int = 100) -> tuple[OdometryGate, list[tuple[str, str, int, int]], Clock]:
    out: list[tuple[str, str, int, int]] = []
    clock = Clock()
    gate = OdometryGate(lambda r, k, p, m, t: out.append((r, k, m.stamp_ns, t)), clock, wait_ns)
    return gate, out, clock


def test_a_scan_before_its_odometry_waits_for_it() -> None:
    gate, out, _ = _gate()
    gate.put("r", "odom", b"", _odom(100))
    gate.put("r", "scan", b"", _scan(200))  # its odometry is not in yet
    assert [k for _, k, _, _ in out] == ["odom"]
    gate.put("r", "odom", b"", _odom(150))
    assert [(r, k) for r, k, _, _ in out] == [("r", "odom"), ("r", "odom")]
    gate.put("r", "odom", b"", _odom(200))
    assert [(k, s) for r, k, s, _ in out if r == "r"][-2:] == [("odom", 200), ("scan", 200)]
    times = [t for _, _, _, t in out]
    assert times == sorted(times)  # handed on with increasing receive times: the log's order
    assert gate.held_count == 1


def test_a_robot_first_scan_waits_for_its_first_odometry_unless_it_sends_none() -> None:
    # After a restart a robot's first scan came before its first odometry and its initial
    # pose, and was matched against the odometry the service held from before: lost, metres off.
    gate, out, clock = _gate(wait_ns=50)
    gate.put("r", "scan", b"", _scan(200))
    assert out == []
    ip = InitialPose(stamp_ns=100, map_id="m", x=0.0, y=0.0, theta=0.0)
    gate.put("r", "initialpose", b"", ip)  # stamped before the held scan: goes on first
    gate.put("r", "odom", b"", _odom(100))
    gate.put("r", "odom", b"", _odom(200))
    assert [(k, s) for _, k, s, _ in out] == [
        ("initialpose", 100),
        ("odom", 100),
        ("odom", 200),
        ("scan", 200),
    ]
    # a robot that sends no odometry waits once, then its scans go on as they come
    gate.put("r2", "scan", b"", _scan(200))
    clock.now += 100
    gate.flush()
    assert out[-1][:3] == ("r2", "scan", 200) and gate.timed_out == 1
    gate.put("r2", "scan", b"", _scan(300))
    assert out[-1][:3] == ("r2", "scan", 300)


def test_held_scans_go_on_when_superseded_timed_out_or_before_a_later_initial_pose() -> None:
    gate, out, clock = _gate(wait_ns=50)
    gate.put("r", "odom", b"", _odom(100))
    gate.put("r", "scan", b"", _scan(200))
    gate.put("r", "scan", b"", _scan(300))  # the first goes on, the second waits
    assert [(k, s) for _, k, s, _ in out] == [("odom", 100), ("scan", 200)]
    gate.flush()
    assert len(out) == 2  # not yet timed out
    clock.now += 100
    gate.flush()
    assert out[-1][1:3] == ("scan", 300) and gate.timed_out == 1
    gate.put("r", "scan", b"", _scan(400))
    ip = InitialPose(stamp_ns=450, map_id="m", x=0.0, y=0.0, theta=0.0)
    gate.put("r", "initialpose", b"", ip)  # stamped after the held scan: the scan goes first
    assert [(k, s) for _, k, s, _ in out[-2:]] == [("scan", 400), ("initialpose", 450)]
    gate.put("r", "scan", b"", _scan(500))
    earlier = InitialPose(stamp_ns=480, map_id="m", x=0.0, y=0.0, theta=0.0)
    gate.put("r", "initialpose", b"", earlier)  # stamped before it: goes on, the scan waits
    assert [(k, s) for _, k, s, _ in out[-2:]] == [("initialpose", 450), ("initialpose", 480)]


def test_every_arrival_order_gives_odometry_first() -> None:
    for order in itertools.permutations(["o1", "s1", "o2", "s2"]):
        if order.index("o1") > order.index("o2") or order.index("s1") > order.index("s2"):
            continue  # each topic keeps its own order
        gate, out, _ = _gate()
        gate.put("r", "odom", b"", _odom(0))
        for item in order:
            stamp = int(item[1]) * 100
            gate.put(
                "r",
                "odom" if item[0] == "o" else "scan",
                b"",
                (_odom if item[0] == "o" else _scan)(stamp),
            )
        gate.flush(all_=True)
        pos = {(k, st): i for i, (_, k, st, _) in enumerate(out)}
        assert [st for _, k, st, _ in out if k == "scan"] == [100, 200]
        # s2 always follows o2; s1 follows o1 unless s2 came before o1 and pushed it on
        assert pos[("scan", 200)] > pos[("odom", 200)]
        if order.index("o1") < order.index("s2"):
            assert pos[("scan", 100)] > pos[("odom", 100)]
