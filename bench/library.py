"""Speed of the algorithm library on one core (targets: update <= 0.3 ms, turning <= 2 ms).

Run: ``python -m bench.library [--updates N] [--write]``. Prints a Markdown table; ``--write``
replaces the library section of ``BENCHMARKS.md``. Times are wall-clock medians, 99th
percentiles and means from one run of ``time.perf_counter``; page faults are the process's minor
faults per call (on VMs they cost microseconds each); peak memory is the process's maximum
resident set size.
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import time

import numpy as np

from bench import bench_turning
from bench.report import section_main
from rlutf.field import DistanceField, WideSearch, wide_search
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.motion import relative, wrap_angle
from rlutf.raycast import Beams, cast_rays
from rlutf.refine import RefineSettings, refine_pose
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)

SECTION = "library"


def _percentiles(samples: list[float]) -> tuple[float, float, float]:
    arr = np.asarray(samples) * 1e3
    return float(np.median(arr)), float(np.percentile(arr, 99)), float(np.mean(arr))


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def bench_localizer(updates: int, config: LocalizerConfig, seed: int = 3) -> dict[str, float]:
    """Median and p99 of one update, 360 beams, on a procedural building of about 100 walls."""
    rng = np.random.default_rng(seed)
    world = make_building(rng)
    truth = make_trajectory(world, rng, updates + 1)
    odom = drift_odometry(truth, OdometryModel(), rng)
    lidar = LidarModel(beams=360)
    scans = [simulate_scan(world, truth[i], lidar, rng) for i in range(1, updates + 1)]
    # Warm up the process (first allocations, lazy imports) on the first scans.
    warm = Localizer(world, truth[0], config, seed=seed)
    for i, scan in enumerate(scans[:20], start=1):
        warm.update(relative(odom[i - 1], odom[i]), scan)
    loc = Localizer(world, truth[0], config, seed=seed)
    times: list[float] = []
    errors: list[float] = []
    headings: list[float] = []
    evaluations: list[int] = []
    faults = _faults()
    for i, scan in enumerate(scans, start=1):
        motion = relative(odom[i - 1], odom[i])
        t0 = time.perf_counter()
        res = loc.update(motion, scan)
        times.append(time.perf_counter() - t0)
        errors.append(math.hypot(*(res.pose[:2] - truth[i, :2])))
        headings.append(float(wrap_angle(res.pose[2] - truth[i, 2])))
        evaluations.append(res.evaluations)
    faults = _faults() - faults
    med, p99, mean = _percentiles(times)
    return {
        "walls": float(len(world.segments)),
        "median_ms": med,
        "p99_ms": p99,
        "mean_ms": mean,
        "mean_evaluations": float(np.mean(evaluations)),
        "rmse_m": float(np.sqrt(np.mean(np.square(errors)))),
        "heading_rmse_deg": math.degrees(float(np.sqrt(np.mean(np.square(headings))))),
        "faults": faults / updates,
    }


def bench_raycast(poses: int, repetitions: int = 500) -> dict[str, float]:
    """Median time of one ``cast_rays`` call, 360 beams, ``poses`` poses, 12 m range."""
    rng = np.random.default_rng(0)
    world = make_building(rng)
    centre = make_trajectory(world, rng, 1)[0]
    p = centre + rng.normal(0.0, [0.05, 0.05, 0.02], (poses, 3))
    beams = Beams.of(np.linspace(-math.pi, math.pi, 360, endpoint=False))
    times = []
    faults = _faults()
    for _ in range(repetitions):
        t0 = time.perf_counter()
        cast_rays(world, p, beams, 12.0)
        times.append(time.perf_counter() - t0)
    faults = _faults() - faults
    med, p99, mean = _percentiles(times)
    return {"median_ms": med, "p99_ms": p99, "mean_ms": mean, "faults": faults / repetitions}


def bench_refine(repetitions: int = 300) -> dict[str, float]:
    """``refine_pose`` of a 360-beam scan from a pose 2 cm and 0.5 deg off."""
    rng = np.random.default_rng(0)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(beams=360), rng)
    valid = scan.valid()
    beams = Beams.of(scan.angles).select(valid)
    start = truth + np.array([0.02, -0.01, math.radians(0.5)])
    settings = RefineSettings()
    times, casts, errors = [], [], []
    for _ in range(repetitions):
        t0 = time.perf_counter()
        fit = refine_pose(
            world, start, beams, scan.ranges[valid], scan.sensor_offset, 12.0, settings
        )
        times.append(time.perf_counter() - t0)
        casts.append(fit.casts)
        errors.append(math.hypot(*(fit.pose[:2] - truth[:2])))
    med, p99, mean = _percentiles(times)
    return {
        "median_ms": med,
        "p99_ms": p99,
        "mean_ms": mean,
        "casts": float(np.mean(casts)),
        "error_mm": 1e3 * float(np.mean(errors)),
    }


def bench_wide(repetitions: int = 50) -> dict[str, float]:
    """The distance field of a building (made once per map) and one wide search."""
    rng = np.random.default_rng(0)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(beams=360), rng)
    valid = scan.valid()
    a = scan.angles[valid]
    points = np.column_stack([scan.ranges[valid] * np.cos(a), scan.ranges[valid] * np.sin(a)])
    t0 = time.perf_counter()
    field = DistanceField.of(world)
    build = time.perf_counter() - t0
    centre = truth + np.array([0.3, -0.3, math.radians(10.0)])
    times = []
    for _ in range(repetitions):
        t0 = time.perf_counter()
        wide_search(world, centre, points, 0.5, math.radians(15.0), WideSearch())[0]
        times.append(time.perf_counter() - t0)
    med, p99, _ = _percentiles(times)
    return {
        "field_ms": build * 1e3,
        "cells": float(field.values.size),
        "median_ms": med,
        "p99_ms": p99,
    }


def render(updates: int) -> str:
    """Run every library benchmark and return the Markdown section."""
    rows = []
    for name, cfg, target in (
        ("Localizer.update, default mode", LocalizerConfig(), "0.3"),
        ("Localizer.update, default without refinement", LocalizerConfig(refine=False), ""),
        ("Localizer.update, mode=paper (turning functions)", LocalizerConfig.paper(), ""),
    ):
        r = bench_localizer(updates, cfg)
        rows.append(
            f"| {name} (360 beams, {int(r['walls'])} walls, {updates} updates) "
            f"| {r['median_ms']:.2f} | {r['p99_ms']:.2f} | {r['mean_ms']:.2f} | {target} "
            f"| {r['mean_evaluations']:.1f} poses scored per update; "
            f"RMSE {r['rmse_m'] * 100:.2f} cm, {r['heading_rmse_deg']:.3f} deg; "
            f"{r['faults']:.1f} page faults per update |"
        )
    for k in (1, 4):
        r = bench_raycast(k)
        rows.append(
            f"| cast_rays, {k} pose(s) x 360 beams | {r['median_ms']:.3f} | {r['p99_ms']:.3f} "
            f"| {r['mean_ms']:.3f} | | {r['faults']:.1f} page faults per call |"
        )
    r = bench_refine()
    rows.append(
        f"| refine_pose, 360 beams, from 2 cm and 0.5 deg off | {r['median_ms']:.3f} "
        f"| {r['p99_ms']:.3f} | {r['mean_ms']:.3f} | | {r['casts']:.1f} casts of the scan; "
        f"ends {r['error_mm']:.2f} mm from the truth |"
    )
    r = bench_wide()
    rows.append(
        f"| wide_search, 0.5 m and 15 deg, 180 points | {r['median_ms']:.2f} | {r['p99_ms']:.2f} "
        f"| | | distance field of the map ({r['cells'] / 1e3:.0f} k cells): "
        f"{r['field_ms']:.0f} ms, once per map version |"
    )
    t = bench_turning.run()
    rows.append(
        f"| turning_distance, two {t['vertices']}-vertex polygons (exact) | {t['median_ms']:.2f} "
        f"| {t['p99_ms']:.2f} | | {t['target_median_ms']} | |"
    )
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return "\n".join(
        [
            f"Command: `python -m bench.library --updates {updates} --write`",
            "",
            f"Machine: {platform.machine()}, {platform.python_implementation()} "
            f"{platform.python_version()}, numpy {np.__version__}; one process, one core. "
            f"Peak resident memory of the run: {rss_mb:.0f} MB.",
            "",
            "| what | median ms | p99 ms | mean ms | target median ms | notes |",
            "| --- | --- | --- | --- | --- | --- |",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    parser = argparse.ArgumentParser(prog="python -m bench.library", description=__doc__)
    parser.add_argument("--updates", type=int, default=300, help="localizer updates per mode")
    return section_main(parser, lambda args: render(args.updates), SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
