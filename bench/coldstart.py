"""Cold and warm start: the time until ``rlutf serve`` is ready and until a robot's first pose.

Run: ``python -m bench.coldstart [--workers 2] [--runs 1]``.

A cold start is the first start after an install: numba's cache is empty, and the kernels are
compiled (by the first worker alone; the others then load them). It is reproduced by pointing
``NUMBA_CACHE_DIR`` at an empty folder. A warm start reuses that folder. For each, one
``rlutf serve`` subprocess (router on a loopback port, embedded store, no recording) is timed
from its start to its ``ready`` line, then a client puts a map, an initial pose, odometry and
scans at 10 Hz, and the time from the ready line to the first pose is taken, with the share of
the robot's scans answered over the first 5 seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan
from schemas import InitialPose, Map, Odometry, encode
from service.live.sessions import client_config, free_port
from service.sim.wire import laser_scan

JSON = zenoh.Encoding.APPLICATION_JSON
SCANS = 50  # 5 s at 10 Hz


def one_start(cache: Path, workers: int, work: Path) -> dict[str, float]:
    """Start a service with numba's cache in ``cache``; time it to ready and to a first pose."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = work / f"serve-{time.monotonic_ns()}.log"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    cmd = [sys.executable, "-m", "service", "serve", "--listen", endpoint, "--no-record"]
    cmd += ["--store", str(work / "store"), "--no-state", "--workers", str(workers)]
    # The robot's run, drawn before the clock starts.
    rng = np.random.default_rng(1)
    world = make_building(np.random.default_rng(11))
    truth = make_trajectory(world, rng, SCANS + 1)
    lidar = LidarModel(beams=360)
    scans = [simulate_scan(world, truth[i], lidar, rng) for i in range(SCANS + 1)]
    started = time.monotonic()
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, stderr=out, env=env)
    try:
        while b"rlutf serve: ready" not in log.read_bytes():
            if proc.poll() is not None:
                raise RuntimeError(f"rlutf serve exited: {log.read_text()[-2000:]}")
            time.sleep(0.05)
        ready = time.monotonic()
        poses: list[float] = []
        with zenoh.open(client_config(endpoint)) as client:
            sub = client.declare_subscriber(
                "rlutf/robots/bench/pose", lambda s: poses.append(time.monotonic())
            )
            m = Map(map_id="m1", version=1, geometry=world.to_geojson())
            client.put("rlutf/maps/m1", encode(m), encoding=JSON)
            t0 = time.time_ns()
            p = truth[0]
            odom = Odometry(stamp_ns=t0, x=float(p[0]), y=float(p[1]), theta=float(p[2]))
            client.put("rlutf/robots/bench/odom", encode(odom), encoding=JSON)
            init = InitialPose(
                stamp_ns=t0, map_id="m1", x=float(p[0]), y=float(p[1]), theta=float(p[2])
            )
            client.put("rlutf/robots/bench/initialpose", encode(init), encoding=JSON)
            for i in range(1, SCANS + 1):
                stamp = t0 + i * 100_000_000
                p = truth[i]
                odom = Odometry(stamp_ns=stamp, x=float(p[0]), y=float(p[1]), theta=float(p[2]))
                client.put("rlutf/robots/bench/odom", encode(odom), encoding=JSON)
                client.put(
                    "rlutf/robots/bench/scan", encode(laser_scan(scans[i], stamp)), encoding=JSON
                )
                time.sleep(0.1)
            time.sleep(1.0)
            sub.undeclare()
    finally:
        proc.terminate()
        proc.wait(20)
    return {
        "ready_s": ready - started,
        "first_pose_s": (poses[0] - ready) if poses else float("nan"),
        "answered": len(poses) / SCANS,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.coldstart", description=__doc__)
    ap.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--runs", type=int, default=1, help="cold and warm pairs (default 1)")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="rlutf-coldstart-") as tmp:
        for run in range(args.runs):
            cache = Path(tmp) / f"cache{run}"
            cache.mkdir()
            for kind in ("cold", "warm"):
                row = {"start": kind, **one_start(cache, args.workers, Path(tmp))}
                rows.append(row)
                print(json.dumps(row), flush=True)
    print()
    print("| start | to ready (s) | ready to first pose (s) | scans answered |")
    print("| --- | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['start']} | {r['ready_s']:.1f} | {r['first_pose_s']:.2f} | "
            f"{100 * r['answered']:.0f} % |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
