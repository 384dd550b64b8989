"""Speed of the algorithm library on one core (issue targets: update <= 1 ms, turning <= 2 ms).

Run: ``python -m bench.library [--updates N] [--write]``. Prints a Markdown table; ``--write``
replaces the library section of ``BENCHMARKS.md``. Times are wall-clock medians and 99th
percentiles from one run of ``time.perf_counter``; peak memory is the process's maximum resident
set size.
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import time
from pathlib import Path

import numpy as np

from bench import bench_turning
from bench.report import replace_section
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.motion import relative
from rlutf.raycast import Beams, cast_rays
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)

SECTION = "library"


def _percentiles(samples: list[float]) -> tuple[float, float]:
    arr = np.asarray(samples) * 1e3
    return float(np.median(arr)), float(np.percentile(arr, 99))


def bench_localizer(updates: int, config: LocalizerConfig, seed: int = 3) -> dict[str, float]:
    """Median and p99 of one update, 360 beams, on a procedural building of about 100 walls."""
    rng = np.random.default_rng(seed)
    world = make_building(rng)
    truth = make_trajectory(world, rng, updates + 1)
    odom = drift_odometry(truth, OdometryModel(), rng)
    lidar = LidarModel(beams=360)
    scans = [simulate_scan(world, truth[i], lidar, rng) for i in range(1, updates + 1)]
    loc = Localizer(world, truth[0], config, seed=seed)
    times: list[float] = []
    errors: list[float] = []
    evaluations: list[int] = []
    for i, scan in enumerate(scans, start=1):
        motion = relative(odom[i - 1], odom[i])
        t0 = time.perf_counter()
        res = loc.update(motion, scan)
        times.append(time.perf_counter() - t0)
        errors.append(math.hypot(*(res.pose[:2] - truth[i, :2])))
        evaluations.append(res.evaluations)
    med, p99 = _percentiles(times)
    return {
        "walls": float(len(world.segments)),
        "median_ms": med,
        "p99_ms": p99,
        "mean_evaluations": float(np.mean(evaluations)),
        "rmse_m": float(np.sqrt(np.mean(np.square(errors)))),
    }


def bench_raycast(poses: int, repetitions: int = 500) -> dict[str, float]:
    """Median time of one ``cast_rays`` call, 360 beams, ``poses`` poses, 12 m range."""
    rng = np.random.default_rng(0)
    world = make_building(rng)
    centre = make_trajectory(world, rng, 1)[0]
    p = centre + rng.normal(0.0, [0.05, 0.05, 0.02], (poses, 3))
    beams = Beams.of(np.linspace(-math.pi, math.pi, 360, endpoint=False))
    times = []
    for _ in range(repetitions):
        t0 = time.perf_counter()
        cast_rays(world, p, beams, 12.0)
        times.append(time.perf_counter() - t0)
    med, p99 = _percentiles(times)
    return {"median_ms": med, "p99_ms": p99}


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
            f"| {r['median_ms']:.2f} | {r['p99_ms']:.2f} | 1.0 "
            f"| {r['mean_evaluations']:.1f} poses scored per update; "
            f"RMSE {r['rmse_m'] * 100:.1f} cm |"
        )
    for k in (1, 4):
        r = bench_raycast(k)
        rows.append(
            f"| cast_rays, {k} pose(s) x 360 beams | {r['median_ms']:.3f} | {r['p99_ms']:.3f} | | |"
        )
    t = bench_turning.run()
    rows.append(
        f"| turning_distance, two {t['vertices']}-vertex polygons (exact) | {t['median_ms']:.2f} "
        f"| {t['p99_ms']:.2f} | {t['target_median_ms']} | |"
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
            "| what | median ms | p99 ms | target median ms | notes |",
            "| --- | --- | --- | --- | --- |",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    parser = argparse.ArgumentParser(prog="python -m bench.library", description=__doc__)
    parser.add_argument("--updates", type=int, default=300, help="localizer updates per mode")
    parser.add_argument("--write", action="store_true", help="update BENCHMARKS.md")
    args = parser.parse_args(argv)
    text = render(args.updates)
    print(text)
    if args.write:
        replace_section(Path("BENCHMARKS.md"), SECTION, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
