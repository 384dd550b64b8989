"""Where a refinement settles (``python -m bench.evenodd --settle``): the offsets and the
refiner, on a drawn room (the CARMEN logs are not in the repository)."""

from __future__ import annotations

import numpy as np
from shapely.geometry import box

from bench.evenodd_runs import rlutf_refiner
from bench.evenodd_settle import SIGMA_THETA, SIGMA_XY, STARTS, correlation, offsets
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map
from rlutf.raycast import cast_rays
from rlutf.scan import Scan


def test_offsets_are_the_same_for_every_method_and_of_the_stated_size() -> None:
    a, b = offsets(2000), offsets(2000)
    assert a.shape == (2000, STARTS, 3)
    assert np.array_equal(a, b)
    spread = a.reshape(-1, 3).std(axis=0)
    assert np.allclose(spread, [SIGMA_XY, SIGMA_XY, SIGMA_THETA], rtol=0.05)


def test_the_refinement_settles_at_the_truth_of_a_noise_free_scan_from_an_offset_start() -> None:
    # An L-shaped room (no symmetry): from every offset the refinement reaches the pose the
    # scan was taken at, so what the section reports is the cost's bottom, not the start.
    world = Map.from_shapely(box(0, 0, 6, 4).difference(box(4, 2, 6, 4)))
    truth = np.array([2.0, 1.5, 0.4])
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = cast_rays(world, truth, angles, 10.0)[0]
    scan = Scan.create(ranges, float(angles[0]), float(angles[1] - angles[0]), 0.05, 10.0)
    refine = rlutf_refiner(world, LocalizerConfig())
    for move in offsets(3)[1]:
        settled = refine(1, scan, truth + move)
        assert np.hypot(*(settled[:2] - truth[:2])) < 1e-3
        assert abs(settled[2] - truth[2]) < 1e-3


def test_the_errors_correlation_is_per_axis_and_leaves_out_failed_scans() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(200, 2))
    b = np.column_stack([2.0 * a[:, 0] + 1.0, -a[:, 1]])
    b[7] = np.inf  # a scan ICP could not align
    cx, cy = correlation(a, b)
    assert np.isclose(cx, 1.0) and np.isclose(cy, -1.0)
    independent = rng.normal(size=(200, 2))
    assert all(abs(c) < 0.3 for c in correlation(a, independent))
