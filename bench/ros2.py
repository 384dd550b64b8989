"""The ROS 2 front door: CDR decode and validation per scan against JSON, and a ROS fleet.

Run: ``python -m bench.ros2 [--robots 25,50] [--duration 15] [--write]``.

1. Per scan, in this process: the JSON front door's work on a LaserScan (``schemas.decode``:
   parse and validate) against the ROS front door's (``service.ros2.convert.laser_scan``: CDR
   decode with rosbags and the same validation, then ``schemas.encode`` of the message, which
   the log records), for 360, 720 and 1440 beams; median of batches, wall and CPU time.
2. The fleet benchmark of :mod:`bench.fleet` with ROS robots (:class:`service.sim.wire.CdrWire`):
   each robot publishes ``nav_msgs/Odometry`` and a 360-beam ``sensor_msgs/LaserScan`` in CDR
   on rmw_zenoh's keys (Jazzy naming, with the 33-byte attachment) at 10 Hz, its initial pose on
   ``initialpose``, and the generator times each scan put to its ``amcl_pose`` (after each
   robot's first 2 s, as for the JSON robots); the JSON fleet runs at the same
   sizes in the same session for comparison. ``rlutf serve --ros2`` also publishes ``tf``
   and the JSON pose for every ROS robot, which the ROS rows pay for.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from typing import Any

import numpy as np

from bench.fleetrun import run_size
from bench.report import section_main

SECTION = "ros2"


# ----------------------------------------------------------------------------- codec
def _scan_payloads(beams: int, seed: int = 1) -> tuple[bytes, bytes]:
    """One simulated scan as the JSON and as the CDR a robot would put."""
    from schemas import LaserScan, encode
    from service.sim.plan import FleetSpec, plan_fleet
    from service.sim.wire import CdrWire

    plan = plan_fleet(FleetSpec(robots=1, poses=2, beams=beams, seed=seed))
    s = plan.robots[0].scans[0]
    stamp = 1_732_300_000_000_000_000
    ranges32 = np.asarray(s.ranges, dtype=np.float32)
    f32 = [float(np.float32(v)) for v in (s.angle_min, s.angle_increment, s.range_min, s.range_max)]
    js = encode(  # the same numbers: LaserScan's fields are float32
        LaserScan(
            stamp_ns=stamp,
            angle_min=f32[0],
            angle_increment=f32[1],
            range_min=f32[2],
            range_max=f32[3],
            ranges=[float(r) if math.isfinite(r) else None for r in ranges32.tolist()],
        )
    )
    return js, CdrWire(plan).scan(0, 0, stamp)


def _per_call_us(fn: Any, reps: int, batches: int = 5) -> tuple[float, float]:
    """Median over batches of (wall, CPU) microseconds per call."""
    walls, cpus = [], []
    for _ in range(batches):
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(reps):
            fn()
        walls.append((time.perf_counter() - w0) / reps * 1e6)
        cpus.append((time.process_time() - c0) / reps * 1e6)
    return float(np.median(walls)), float(np.median(cpus))


def codec_rows(reps: int) -> list[str]:
    """Table rows: beams, bytes, JSON decode, CDR decode, CDR decode + JSON encode."""
    from schemas import LaserScan, decode, encode
    from service.ros2 import convert

    rows = []
    for beams in (360, 720, 1440):
        js, cdr = _scan_payloads(beams)
        assert decode(LaserScan, js) == convert.laser_scan(cdr)  # the same message both ways
        j = _per_call_us(lambda js=js: decode(LaserScan, js), reps)
        c = _per_call_us(lambda cdr=cdr: convert.laser_scan(cdr), reps)
        ce = _per_call_us(lambda cdr=cdr: convert.wire_json(convert.laser_scan(cdr)), reps)
        slow = _per_call_us(lambda cdr=cdr: encode(convert.laser_scan(cdr)), max(reps // 10, 1))
        raw = _per_call_us(lambda cdr=cdr: convert.deserialize(cdr, convert.LASER_SCAN), reps)
        rows.append(
            f"| {beams} | {len(js)} / {len(cdr)} | {j[0]:.0f} ({j[1]:.0f}) "
            f"| {raw[0]:.1f} ({raw[1]:.1f}) | {c[0]:.0f} ({c[1]:.0f}) | {ce[0]:.0f} ({ce[1]:.0f}) "
            f"| {slow[0]:.0f} ({slow[1]:.0f}) |"
        )
        print(rows[-1], flush=True)
    return rows


# ----------------------------------------------------------------------------- fleet
def fleet_rows(sizes: list[int], duration: float, workers: int) -> list[str]:
    """Table rows: the JSON and the ROS fleet at each size."""
    rows = []
    for n in sizes:
        for door in ("JSON", "ROS 2"):
            if door == "JSON":
                r = run_size(n, duration, True, workers)
            else:
                flags = ("--ros2", "--ros-map", "bench")
                r = run_size(n, duration, True, workers, "ros2", flags)
            ok = r["p99"] <= 50.0 and r["uncounted"] == 0 and r["dropped"] <= 0.01 * r["sent"]
            rows.append(
                f"| {door} | {n} | {r['sent']} | {r['poses']} | {r['dropped']} "
                f"| {r['p50']:.1f} | {r['p99']:.1f} "
                f"| {r['cpu_main']:.2f} / {r['cpu_workers']:.2f} / {r['cpu_generator']:.2f} "
                f"| {r['cpu_service_per_pose']:.2f} | {'yes' if ok else 'no'} |"
            )
            print(rows[-1], flush=True)
    return rows


def render(args: argparse.Namespace) -> str:
    """Run both parts and return the Markdown section."""
    sizes = [int(s) for s in args.robots.split(",")] if args.robots else []
    load = os.getloadavg()[0]
    codec = codec_rows(args.reps)
    fleet = fleet_rows(sizes, args.duration, args.workers) if sizes else []
    flags = f" --robots {args.robots}" if sizes else " --robots ''"
    lines = [
        f"Command: `python -m bench.ros2{flags} --duration {args.duration:g} "
        f"--reps {args.reps} --write`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
        f"{platform.python_version()}; load average at the start {load:.1f} (2 cores shared "
        "with other work: read ratios).",
        "",
        "Per scan, one process, median of 5 batches: microseconds of wall time (CPU time in "
        "brackets). JSON: `schemas.decode` of the payload a JSON robot puts. CDR: rosbags' "
        "`deserialize_cdr` alone, then `service.ros2.convert.laser_scan` (decode, NaN to no "
        "return, the same pydantic validation), then that plus the JSON the log records "
        "(`convert.wire_json`, pydantic's serializer; `schemas.encode` for comparison, whose "
        "float `repr` is the cost). The JSON front door records the bytes it received.",
        "",
        "| beams | payload bytes JSON / CDR | JSON decode + validate us | CDR decode only us "
        "| CDR decode + validate us | CDR + JSON for the log us | same with `schemas.encode` us |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        *codec,
    ]
    if fleet:
        lines += [
            "",
            f"Fleet, as `python -m bench.fleet` (recording on, {args.duration:g} s per size at "
            "10 Hz per robot, 360-beam scans): the JSON robots, then ROS robots on rmw_zenoh's "
            "keys against `rlutf serve --ros2`, which also publishes `tf` and the JSON pose. "
            "Latency is scan put to pose put (`amcl_pose` for ROS).",
            "",
            "| front door | robots | scans sent | poses | dropped | latency p50 ms | p99 ms "
            "| CPU ms per scan: service main / workers / generator "
            "| service CPU ms per pose | held (p99 <= 50 ms, drops <= 1 %) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            *fleet,
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.ros2",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", default="25,50", help="fleet sizes ('' for the codec only)")
    p.add_argument("--duration", type=float, default=15.0, help="seconds per fleet size")
    p.add_argument("--reps", type=int, default=2000, help="calls per batch in the codec part")
    p.add_argument("--workers", type=int, default=-1, help="service worker processes")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
