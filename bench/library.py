"""Speed of the algorithm library on one core (issue targets: update <= 1 ms, turning <= 2 ms).

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
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.motion import relative, wrap_angle
from rlutf.raycast import Beams, cast_rays
from rlutf.region import RegionCaster
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


def bench_region(poses: int, repetitions: int = 500) -> dict[str, float]:
    """``RegionCaster``: preparing one (2 cm, 10 mrad region) and casting ``poses`` poses."""
    rng = np.random.default_rng(0)
    world = make_building(rng)
    centre = make_trajectory(world, rng, 1)[0]
    p = centre + rng.normal(0.0, [0.005, 0.005, 0.003], (poses, 3))
    beams = Beams.of(np.linspace(-math.pi, math.pi, 360, endpoint=False))
    setup, cast = [], []
    pairs = 0
    for _ in range(repetitions):
        t0 = time.perf_counter()
        caster = RegionCaster(world, beams, centre, 0.02, 0.01, 12.0)
        t1 = time.perf_counter()
        caster.cast(p)
        cast.append(time.perf_counter() - t1)
        setup.append(t1 - t0)
        pairs = caster.pairs
    s_med, s_p99, _ = _percentiles(setup)
    c_med, c_p99, _ = _percentiles(cast)
    return {
        "setup_ms": s_med,
        "setup_p99_ms": s_p99,
        "cast_ms": c_med,
        "cast_p99_ms": c_p99,
        "pairs": float(pairs),
    }


def render(updates: int) -> str:
    """Run every library benchmark and return the Markdown section."""
    rows = []
    for name, cfg in (
        ("Localizer.update, default mode", LocalizerConfig()),
        ("Localizer.update, mode=paper", LocalizerConfig.paper()),
    ):
        r = bench_localizer(updates, cfg)
        rows.append(
            f"| {name} (360 beams, {int(r['walls'])} walls, {updates} updates) "
            f"| {r['median_ms']:.2f} | {r['p99_ms']:.2f} | {r['mean_ms']:.2f} | 1.0 "
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
    for k in (1, 9):
        r = bench_region(k)
        rows.append(
            f"| RegionCaster: prepare (2 cm, 10 mrad region) + cast {k} pose(s) x 360 beams "
            f"| {r['setup_ms']:.3f} + {r['cast_ms']:.3f} | {r['setup_p99_ms']:.3f} + "
            f"{r['cast_p99_ms']:.3f} | | | {int(r['pairs'])} (wall, beam) pairs |"
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
