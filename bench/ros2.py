"""The ROS 2 front door: CDR decode and validation per scan against JSON, and a ROS fleet.

Run: ``python -m bench.ros2 [--robots 25,50] [--duration 15] [--write]``.

1. Per scan, in this process: the JSON front door's work on a LaserScan (``schemas.decode``:
   parse and validate) against the ROS front door's (``service.ros2.convert.laser_scan``: CDR
   decode with rosbags and the same validation, then ``schemas.encode`` of the message, which
   the log records), for 360, 720 and 1440 beams; median of batches, wall and CPU time.
2. The fleet benchmark of :mod:`bench.fleet` with ROS robots: each robot publishes
   ``nav_msgs/Odometry`` and a 360-beam ``sensor_msgs/LaserScan`` in CDR on rmw_zenoh's keys
   (Jazzy naming, with the 33-byte attachment) at 10 Hz, its initial pose on ``initialpose``,
   and the generator times each scan put to its ``amcl_pose``; the JSON fleet runs at the same
   sizes in the same session for comparison. ``rlutf serve --ros2`` also publishes ``tf``
   and the JSON pose for every ROS robot, which the ROS rows pay for.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import struct
import threading
import time
from typing import Any

import numpy as np

from bench.fleet import RATE_HZ, generator_result, run_size, timed_publishing
from bench.report import section_main

SECTION = "ros2"


# ----------------------------------------------------------------------------- codec
def _scan_payloads(beams: int, seed: int = 1) -> tuple[bytes, bytes]:
    """One simulated scan as the JSON and as the CDR a robot would put."""
    from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan
    from schemas import LaserScan, encode
    from service.ros2 import convert

    rng = np.random.default_rng(seed)
    world = make_building(rng)
    pose = make_trajectory(world, rng, 2)[0]
    s = simulate_scan(world, pose, LidarModel(beams=beams), rng)
    ranges32 = np.asarray(s.ranges, dtype=np.float32)
    f32 = [float(np.float32(v)) for v in (s.angle_min, s.angle_increment, s.range_min, s.range_max)]
    js = encode(  # the same numbers: LaserScan's fields are float32
        LaserScan(
            stamp_ns=1_732_300_000_000_000_000,
            angle_min=f32[0],
            angle_increment=f32[1],
            range_min=f32[2],
            range_max=f32[3],
            ranges=[float(r) if math.isfinite(r) else None for r in ranges32.tolist()],
        )
    )
    t = convert.typestore().types
    msg = t[convert.LASER_SCAN](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=1_732_300_000, nanosec=0), frame_id="laser"
        ),
        angle_min=s.angle_min,
        angle_max=s.angle_min + s.angle_increment * (beams - 1),
        angle_increment=s.angle_increment,
        time_increment=0.0,
        scan_time=0.1,
        range_min=s.range_min,
        range_max=s.range_max,
        ranges=ranges32,
        intensities=np.zeros(0, dtype=np.float32),
    )
    return js, convert.serialize(msg, convert.LASER_SCAN)


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
def _ros_generator(
    endpoint: str,
    robots: int,
    duration: float,
    seed: int,
    out: Any,
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
) -> None:
    """Load generator of ROS robots (a separate process), as :func:`bench.fleet._generator`."""
    import zenoh

    from rlutf.sim import (
        LidarModel,
        OdometryModel,
        drift_odometry,
        make_building,
        make_trajectory,
        simulate_scan,
    )
    from schemas import Map, encode
    from service.live.sessions import client_config
    from service.ros2 import convert, names

    ts = convert.typestore()
    t = ts.types
    rng = np.random.default_rng(seed)
    world = make_building(rng)
    steps = int(duration * RATE_HZ) + 1
    lidar = LidarModel(beams=360)

    def header(stamp: int, frame: str) -> Any:
        sec, ns = divmod(stamp, 1_000_000_000)
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame
        )

    def pose_msg(p: np.ndarray) -> Any:
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(p[2] / 2), w=math.cos(p[2] / 2)
            ),
        )

    cov = np.zeros(36)
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
    )
    plans = []
    for i in range(robots):
        truth = make_trajectory(world, rng, steps, dt=1.0 / RATE_HZ)
        odom = drift_odometry(truth, OdometryModel(), rng)
        scans = []
        for k in range(steps):
            s = simulate_scan(world, truth[k], lidar, rng)
            scans.append(
                t[convert.LASER_SCAN](
                    header=header(0, "laser"),
                    angle_min=s.angle_min,
                    angle_max=s.angle_min + s.angle_increment * (len(s.ranges) - 1),
                    angle_increment=s.angle_increment,
                    time_increment=0.0,
                    scan_time=0.1,
                    range_min=s.range_min,
                    range_max=s.range_max,
                    ranges=np.asarray(s.ranges, dtype=np.float32),
                    intensities=np.zeros(0, dtype=np.float32),
                )
            )
        odoms = [
            t[convert.ODOMETRY](
                header=header(0, "odom"),
                child_frame_id="base_footprint",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(o), covariance=cov),
                twist=twist,
            )
            for o in odom
        ]
        plans.append((f"r{i:03d}", truth, odoms, scans))
    sessions = [zenoh.open(client_config(endpoint)) for _ in range(max(1, min(8, robots // 12)))]
    op = sessions[0]
    geometry = world.to_geojson()
    op.put(
        "rlutf/maps/bench",
        encode(Map.model_validate({"map_id": "bench", "version": 1, "geometry": geometry})),
    )
    sent: dict[tuple[str, int], int] = {}
    latencies: list[float] = []
    poses = 0
    lock = threading.Lock()

    def on_pose(sample: Any) -> None:
        nonlocal poses
        now = time.time_ns()
        robot = str(sample.key_expr).split("/")[1]
        h = ts.deserialize_cdr(sample.payload.to_bytes(), convert.POSE_COV).header
        stamp = h.stamp.sec * 1_000_000_000 + h.stamp.nanosec
        with lock:
            sent_at = sent.pop((robot, stamp), None)
            poses += 1
            if sent_at is not None:
                latencies.append((now - sent_at) / 1e6)

    sub = op.declare_subscriber("0/*/amcl_pose/*/*", on_pose)
    time.sleep(1.0)
    t0 = time.time_ns()
    seq = [0] * robots
    gids = [struct.pack("<QQ", i + 1, seed) for i in range(robots)]

    def put(pub: Any, i: int, raw: bytes) -> None:
        seq[i] += 1
        pub.put(raw, attachment=struct.pack("<qqB", seq[i], time.time_ns(), 16) + gids[i])

    pubs = []
    for idx, (rid, truth, odoms, _) in enumerate(plans):
        sess = sessions[idx % len(sessions)]
        key = {
            name: names.data_key(0, f"/{rid}/{name}", mt, "jazzy")
            for name, mt in (
                ("odom", convert.ODOMETRY),
                ("scan", convert.LASER_SCAN),
                ("initialpose", convert.POSE_COV),
            )
        }
        p_odom, p_scan = sess.declare_publisher(key["odom"]), sess.declare_publisher(key["scan"])
        odoms[0].header = header(t0, "odom")
        put(p_odom, idx, convert.serialize(odoms[0], convert.ODOMETRY))
        ip = t[convert.POSE_COV](
            header=header(t0, "map"),
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(truth[0]), covariance=cov),
        )
        sess.put(key["initialpose"], convert.serialize(ip, convert.POSE_COV))
        pubs.append((p_odom, p_scan))

    def send(i: int, k: int, stamp: int) -> None:
        rid, _, odoms, scans = plans[i]
        # Serialized at publication, as a ROS node does (a few microseconds with rosbags).
        odoms[k + 1].header = header(stamp, "odom")
        scans[k + 1].header = header(stamp, "laser")
        put(pubs[i][0], i, convert.serialize(odoms[k + 1], convert.ODOMETRY))
        with lock:
            sent[(rid, stamp)] = time.time_ns()
        put(pubs[i][1], i, convert.serialize(scans[k + 1], convert.LASER_SCAN))

    scans_sent, behind, cpu = timed_publishing(robots, steps, t0, send, ready, go, began, ended)
    time.sleep(2.0)  # the last poses
    sub.undeclare()
    for s in sessions:
        s.close()
    out.put(generator_result(scans_sent, poses, latencies, behind, cpu))


def fleet_rows(sizes: list[int], duration: float, workers: int) -> list[str]:
    """Table rows: the JSON and the ROS fleet at each size."""
    rows = []
    for n in sizes:
        for door in ("JSON", "ROS 2"):
            if door == "JSON":
                r = run_size(n, duration, True, workers)
            else:
                flags = ("--ros2", "--ros-map", "bench")
                r = run_size(n, duration, True, workers, _ros_generator, flags)
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
