"""Three good robots driving at 10 Hz beside an attack (:mod:`bench.adversarial`).

:func:`drive` runs in a process of its own: it simulates each robot's run on the map ``bench``
(truth, drifting odometry, 360-beam scans with 1 cm noise) before the clock starts, places the
robots (:func:`open_fleet`), then publishes odometry and a scan per robot every
0.1 s and records every pose it receives. :func:`score` reads what the attack did to them.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from typing import Any

import numpy as np

GOOD = ("g0", "g1", "g2")
RATE_HZ = 10.0
#: Scans of each robot not counted: the first after the initial pose searches wide.
WARMUP_S = 2.0


def drive(endpoint: str, duration: float, seed: int, out: Any, ready: Any, go: Any) -> None:
    """Drive the good robots for ``duration`` seconds once ``go`` is set (a process target).

    Puts on ``out`` first the robots' start poses, then the result :func:`score` reads.
    """
    from rlutf.sim import (
        LidarModel,
        OdometryModel,
        drift_odometry,
        make_building,
        make_trajectory,
        simulate_scan,
    )

    rng = np.random.default_rng(seed)
    world = make_building(rng)
    steps = int(duration * RATE_HZ) + 1
    lidar = LidarModel(beams=360)
    plans = []
    for rid in GOOD:
        truth = make_trajectory(world, rng, steps, dt=1.0 / RATE_HZ)
        odom = drift_odometry(truth, OdometryModel(), rng)
        scans = []
        for k in range(steps):
            s = simulate_scan(world, truth[k], lidar, rng)
            ranges = [round(float(r), 4) if math.isfinite(r) else None for r in s.ranges]
            head = {"angle_min": s.angle_min, "angle_increment": s.angle_increment}
            body = {**head, "range_min": s.range_min, "range_max": s.range_max, "ranges": ranges}
            scans.append(json.dumps(body)[1:])
        plans.append((rid, truth, odom, scans))
    poses: list[tuple[str, int, float, float, float, str]] = []
    lock = threading.Lock()

    def on_pose(sample: Any) -> None:
        now = time.monotonic()
        try:
            d = json.loads(sample.payload.to_bytes())
            row = (d["robot_id"], int(d["stamp_ns"]), now, d["x"], d["y"], d["status"])
        except (ValueError, KeyError, TypeError):
            return
        with lock:
            poses.append(row)

    starts = [(rid, odom[0], truth[0]) for rid, truth, odom, _ in plans]
    session, sub, pubs, t0 = open_fleet(endpoint, world, starts, on_pose)
    out.put({rid: tuple(float(v) for v in truth[0]) for rid, truth, _, _ in plans})
    ready.set()
    go.wait()
    sent: list[tuple[str, int, int, float]] = []
    period = 1.0 / RATE_HZ
    start = time.monotonic()
    for k in range(1, steps):
        for i, (rid, _, odom, scans) in enumerate(plans):
            when = start + (k - 1 + i / len(plans)) * period
            delay = when - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            stamp = t0 + int(k * period * 1e9)
            o = odom[k]
            pubs[i][0].put(
                json.dumps(
                    {"stamp_ns": stamp, "x": float(o[0]), "y": float(o[1]), "theta": float(o[2])}
                )
            )
            pubs[i][1].put(f'{{"stamp_ns": {stamp}, ' + scans[k])
            sent.append((rid, stamp, k, time.monotonic()))
    end = time.monotonic()
    time.sleep(2.0)  # the last poses
    sub.undeclare()
    session.close()
    with lock:
        got = list(poses)
    truths = {rid: truth.tolist() for rid, truth, _, _ in plans}
    out.put({"sent": sent, "poses": got, "truth": truths, "start": start, "end": end})


def open_fleet(
    endpoint: str, world: Any, starts: list[tuple[str, Any, Any]], on_pose: Any
) -> tuple[Any, Any, list[tuple[Any, Any]], int]:
    """Put the map ``bench``, follow every pose, place the robots (first odometry, initial
    pose stamped ``t0``) and declare their publishers.

    Returns:
        The session, the pose subscriber, per robot its (odometry, scan) publishers, and t0.
    """
    import zenoh

    from schemas import InitialPose, Map, encode
    from service.live.sessions import client_config

    session = zenoh.open(client_config(endpoint))
    body = {"map_id": "bench", "version": 1, "geometry": world.to_geojson()}
    session.put("rlutf/maps/bench", encode(Map.model_validate(body)))
    sub = session.declare_subscriber("rlutf/robots/*/pose", on_pose)
    time.sleep(1.0)
    t0 = time.time_ns()
    pubs = []
    for rid, o, p in starts:
        odom = {"stamp_ns": t0, "x": float(o[0]), "y": float(o[1]), "theta": float(o[2])}
        session.put(f"rlutf/robots/{rid}/odom", json.dumps(odom))
        start = InitialPose(
            stamp_ns=t0, map_id="bench", x=float(p[0]), y=float(p[1]), theta=float(p[2])
        )
        session.put(f"rlutf/robots/{rid}/initialpose", encode(start))
        pubs.append(
            (
                session.declare_publisher(f"rlutf/robots/{rid}/odom"),
                session.declare_publisher(f"rlutf/robots/{rid}/scan"),
            )
        )
    return session, sub, pubs, t0


def score(result: dict[str, Any], attack_start: float) -> dict[str, Any]:
    """What an attack did to the good robots.

    Returns:
        ``answered``: share of the scans sent after the warm-up that got their pose;
        ``gap``: the longest any robot went without a pose from the attack's start to the end
        of sending, seconds; ``error``: the largest distance of a pose not ``lost`` from the
        truth, metres; ``scans`` and ``poses`` counted.
    """
    warm_end = result["start"] + WARMUP_S
    sent = {(rid, stamp): (k, t) for rid, stamp, k, t in result["sent"]}
    answered: set[tuple[str, int]] = set()
    receipts: dict[str, list[float]] = {rid: [] for rid in result["truth"]}
    error = 0.0
    for rid, stamp, t, x, y, status in result["poses"]:
        found = sent.get((rid, stamp))
        if found is None:
            continue  # not a pose of ours (a forged one, or of an attacker's robot)
        k, t_sent = found
        answered.add((rid, stamp))
        receipts[rid].append(t)
        if status != "lost" and t_sent >= warm_end:
            tx, ty, _ = result["truth"][rid][k]
            error = max(error, math.hypot(x - tx, y - ty))
    counted = [key for key, (_, t) in sent.items() if t >= warm_end]
    share = sum(1 for key in counted if key in answered) / max(len(counted), 1)
    gap = 0.0
    for times in receipts.values():
        inside = sorted(t for t in times if attack_start <= t <= result["end"])
        edges = [attack_start, *inside, result["end"]]
        gap = max(gap, *(b - a for a, b in itertools.pairwise(edges)))
    return {
        "answered": share,
        "gap": gap,
        "error": error,
        "scans": len(counted),
        "poses": len(answered),
    }
