"""Helpers for the MCAP, replay and log-tool tests: simulated runs written as logs."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rlutf.map import Map as World
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)
from schemas import InitialPose, LaserScan, Map, Odometry, encode
from service.logs.mcapfile import LogWriter, Record
from service.logs.mcapread import LogFile

T0 = 1_732_300_000_000_000_000
STEP_NS = 100_000_000
WORLD = make_building(np.random.default_rng(5))


def simulated_inputs(
    robots: Sequence[str] = ("r1", "r2"),
    steps: int = 20,
    seed: int = 3,
    beams: int = 120,
    prefix: str = "rlutf",
    world: World | None = None,
    seen: Callable[[list[np.ndarray]], Any] | None = None,
) -> list[Record]:
    """A map (``world``, default :data:`WORLD`), initial poses, then odometry and a scan per
    robot per step, in log order; the scans are of the world ``seen`` makes of the robots'
    paths (a :class:`rlutf.map.Map`; default: the map itself).

    ``log_time`` is strictly increasing: 1 ms after the stamp, plus 10 us per robot.
    """
    rng = np.random.default_rng(seed)
    building = WORLD if world is None else world
    out = [
        Record(
            f"{prefix}/maps/m1",
            "rlutf.Map",
            encode(Map(map_id="m1", version=1, geometry=building.to_geojson())),
            T0 - 1_000_000,
            T0 - 1_000_000,
        )
    ]
    runs = {}
    for k, robot in enumerate(robots):
        truth = make_trajectory(building, rng, steps + 1)
        odom = drift_odometry(truth, OdometryModel(), rng)
        runs[robot] = (truth, odom)
        start = InitialPose(
            stamp_ns=T0,
            map_id="m1",
            x=float(truth[0, 0]) + 0.05,
            y=float(truth[0, 1]),
            theta=float(truth[0, 2]),
        )
        out.append(
            Record(
                f"{prefix}/robots/{robot}/initialpose",
                "rlutf.InitialPose",
                encode(start),
                T0 + 10_000 * k,
                T0,
            )
        )
    lidar = LidarModel(beams=beams)
    scanned = building if seen is None else seen([truth for truth, _ in runs.values()])
    for i in range(steps + 1):
        stamp = T0 + i * STEP_NS
        for k, (robot, (truth, odom)) in enumerate(runs.items()):
            at = stamp + 1_000_000 + 10_000 * k
            o = Odometry(
                stamp_ns=stamp, x=float(odom[i, 0]), y=float(odom[i, 1]), theta=float(odom[i, 2])
            )
            out.append(
                Record(f"{prefix}/robots/{robot}/odom", "rlutf.Odometry", encode(o), at, stamp)
            )
            if i == 0:
                continue
            s = simulate_scan(scanned, truth[i], lidar, rng)
            scan = LaserScan(
                stamp_ns=stamp,
                angle_min=s.angle_min,
                angle_increment=s.angle_increment,
                range_min=s.range_min,
                range_max=s.range_max,
                ranges=[float(r) if math.isfinite(r) else None for r in s.ranges],
            )
            out.append(
                Record(
                    f"{prefix}/robots/{robot}/scan",
                    "rlutf.LaserScan",
                    encode(scan),
                    at + 1_000,
                    stamp,
                )
            )
    return out


def write_log(
    path: Path,
    records: Iterable[Record],
    config: dict[str, Any] | None = None,
    chunk_size: int = 1 << 20,
) -> Path:
    """Write records (no Foxglove views) into a complete log."""
    with open(path, "wb") as stream:
        writer = LogWriter(stream, chunk_size=chunk_size)
        if config is not None:
            writer.write_config(config)
        writer.write_all(records)
        writer.finish()
    return path


def read_all(path: Path, schema_names: Iterable[str] | None = None) -> list[Record]:
    """Every message of a log in log-time order."""
    with LogFile(path) as lf:
        return list(lf.messages(None if schema_names is None else set(schema_names)))


def payloads(path: Path, schema_name: str) -> list[bytes]:
    """Payloads of one schema in log-time order."""
    return [r.payload for r in read_all(path, [schema_name])]
