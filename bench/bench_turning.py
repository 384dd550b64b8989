"""Benchmark: exact turning-function distance of two random 100-vertex polygons.

``run()`` times :func:`rlutf.turning.turning_distance` on one fixed pair of random simple
(star-shaped) polygons and returns the median and 99th-percentile wall time in milliseconds.
The target is a median of at most 2 ms on one core.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numpy.typing import NDArray

from rlutf.turning import turning_distance

VERTICES = 100
REPETITIONS = 200
WARMUP = 10
SEED = 20240601
TARGET_MEDIAN_MS = 2.0


def random_star_polygon(rng: np.random.Generator, vertices: int) -> NDArray[np.float64]:
    """A simple polygon: random radii at increasing angles, every angular gap below pi.

    Args:
        rng: random generator.
        vertices: number of vertices, >= 3.

    Returns:
        Vertices, shape ``(vertices, 2)``, counter-clockwise, within the unit disc.
    """
    gaps = rng.uniform(1.0, 1.9, vertices)
    angles = 2.0 * math.pi * np.cumsum(gaps) / gaps.sum()
    radii = rng.uniform(0.3, 1.0, vertices)
    return np.column_stack((radii * np.cos(angles), radii * np.sin(angles)))


def run() -> dict[str, float | int | str]:
    """Time ``turning_distance`` on two random 100-vertex polygons.

    Returns:
        ``name``, ``vertices``, ``repetitions``, ``median_ms``, ``p99_ms`` and
        ``target_median_ms``; times are ``time.perf_counter`` wall time per call.
    """
    rng = np.random.default_rng(SEED)
    a = random_star_polygon(rng, VERTICES)
    b = random_star_polygon(rng, VERTICES)
    for _ in range(WARMUP):
        turning_distance(a, b)
    times = np.empty(REPETITIONS)
    for k in range(REPETITIONS):
        start = time.perf_counter()
        turning_distance(a, b)
        times[k] = time.perf_counter() - start
    return {
        "name": "turning_distance",
        "vertices": VERTICES,
        "repetitions": REPETITIONS,
        "median_ms": float(np.median(times)) * 1e3,
        "p99_ms": float(np.percentile(times, 99)) * 1e3,
        "target_median_ms": TARGET_MEDIAN_MS,
    }


if __name__ == "__main__":
    print(run())
