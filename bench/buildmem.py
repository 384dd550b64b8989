"""``rlutf map build``'s memory against the length of the recording it reads.

Run: ``python -m bench.buildmem [--scans 6000,24000] [--write]``.

A map is built from a mapping run, and a run of half an hour at 40 Hz is 72,000 scans: what the
build holds must not grow with them. For each length, one simulated robot
(:mod:`service.sim`, 360-beam scans, driven back and forth along its planned path) is written
as a ROS 2 bag (rosbag2, MCAP storage: ``/r0/scan`` and its pose on ``/r0/amcl_pose``, as a
robot running AMCL records them) and as an ``rlutf`` MCAP log (its inputs replayed into a log
that holds a pose per scan, :func:`bench.replaymem.make_log`), each in a process of its own;
then ``rlutf map build`` reads each in a fresh process. Peak resident memory is the process's
``ru_maxrss``; time is wall-clock.
"""

from __future__ import annotations

import argparse
import math
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.replaymem import PLAN_POSES, make_log_apart, peak
from bench.report import ints_text, section_main

SECTION = "buildmem"
T0 = 1_732_300_000_000_000_000
#: Scans of the bag, 40 Hz.
STEP_NS = 25_000_000
SCAN_TOPIC = "/r0/scan"
POSE_TOPIC = "/r0/amcl_pose"


def make_bag(folder: Path, scans: int) -> Path:
    """A rosbag2 of one simulated robot's ``scans`` scans, each with its pose at its stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from service.ros2 import convert
    from service.sim.plan import FleetSpec, plan_fleet
    from service.sim.wire import CdrWire

    plan = plan_fleet(FleetSpec(robots=1, poses=PLAN_POSES, seed=3, map_id="m1"))
    wire = CdrWire(plan)
    robot = plan.robots[0]
    t = convert.typestore().types
    bag = folder / f"bag-{scans}"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        scan_conn = w.add_connection(SCAN_TOPIC, convert.LASER_SCAN, typestore=convert.typestore())
        pose_conn = w.add_connection(POSE_TOPIC, convert.POSE_COV, typestore=convert.typestore())
        for step in range(scans):
            stamp = T0 + step * STEP_NS
            w.write(scan_conn, stamp, wire.scan(0, step, stamp))
            x, y, theta = (float(v) for v in robot.truth[robot.index(step)])
            sec, ns = divmod(stamp, 1_000_000_000)
            msg = t[convert.POSE_COV](
                header=t["std_msgs/msg/Header"](
                    stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id="map"
                ),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](
                    pose=t["geometry_msgs/msg/Pose"](
                        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                        orientation=t["geometry_msgs/msg/Quaternion"](
                            x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2)
                        ),
                    ),
                    covariance=np.zeros(36),
                ),
            )
            w.write(pose_conn, stamp, convert.serialize(msg, convert.POSE_COV))
    return bag


def make_bag_apart(folder: Path, scans: int) -> Path:
    """:func:`make_bag` in a process of its own (see :func:`bench.replaymem.make_log_apart`)."""
    code = (
        "import sys; from pathlib import Path; from bench.buildmem import make_bag; "
        "make_bag(Path(sys.argv[1]), int(sys.argv[2]))"
    )
    subprocess.run([sys.executable, "-c", code, str(folder), str(scans)], check=True)
    return folder / f"bag-{scans}"


def measure(scans: int, folder: Path) -> dict[str, float]:
    rlutf = str(Path(sys.executable).with_name("rlutf"))
    bag = make_bag_apart(folder, scans)
    topics = ["--scan-topic", SCAN_TOPIC, "--pose-topic", POSE_TOPIC]
    out = ["--id", "built", "--out", str(folder / "built.json")]
    bag_mb, bag_s, code = peak([rlutf, "map", "build", str(bag), "--ros2", *topics, *out])
    if code != 0:
        raise RuntimeError(f"rlutf map build {bag} --ros2: exit {code}")
    # The log: one robot, the same scans (at 10 Hz: the simulated fleet's rate).
    log, _ = make_log_apart(folder, 1, scans)
    log_mb, log_s, code = peak([rlutf, "map", "build", str(log), *out])
    if code != 0:
        raise RuntimeError(f"rlutf map build {log}: exit {code}")
    return {"scans": scans, "bag_mb": bag_mb, "bag_s": bag_s, "log_mb": log_mb, "log_s": log_s}


def render(args: argparse.Namespace) -> str:
    sizes = [int(s) for s in args.scans.split(",")]
    with tempfile.TemporaryDirectory(prefix="rlutf-buildmem-") as tmp:
        rows = [measure(n, Path(tmp)) for n in sizes]
    lines = [
        f"Command: `python -m bench.buildmem --scans {args.scans} --write`",
        "",
        f"Machine: {platform.machine()}, CPython {platform.python_version()}; one simulated "
        "robot, 360-beam scans; each recording read by `rlutf map build` in a fresh process.",
        "",
        "| scans | ROS 2 bag (`--ros2`): peak MB | s | rlutf MCAP log: peak MB | s |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {r['scans']:.0f} | {r['bag_mb']:.0f} | {r['bag_s']:.1f} | {r['log_mb']:.0f} | "
        f"{r['log_s']:.1f} |"
        for r in rows
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.buildmem", description=__doc__)
    parser.add_argument(
        "--scans",
        type=ints_text(1),
        default="6000,24000",
        help="scans of each recording, comma-separated",
    )
    return section_main(parser, render, SECTION, argv)


if __name__ == "__main__":
    sys.exit(main())
