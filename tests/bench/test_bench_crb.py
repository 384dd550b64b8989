"""The Cramer-Rao bound of a scan: exact derivatives, and a case with a closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import box

from bench.crb import fisher_information, position_bound, range_jacobian, scan_bound
from rlutf.map import Map
from rlutf.raycast import cast_rays
from rlutf.scan import Scan
from rlutf.sim import make_building, make_trajectory


def test_derivatives_match_finite_differences() -> None:
    world = make_building(np.random.default_rng(4))
    pose = make_trajectory(world, np.random.default_rng(5), 1)[0]
    angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    offset = np.array([0.2, -0.1, 0.3])
    _, jac = range_jacobian(world, pose, angles, offset, 12.0)
    h = 1e-6
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        ranges = []
        for sign in (1.0, -1.0):
            p = pose + sign * step
            c, s = math.cos(p[2]), math.sin(p[2])
            sensor = np.array(
                [
                    p[0] + c * offset[0] - s * offset[1],
                    p[1] + s * offset[0] + c * offset[1],
                    p[2] + offset[2],
                ]
            )
            ranges.append(cast_rays(world, sensor[None], angles, 12.0)[0])
        fd = (ranges[0] - ranges[1]) / (2 * h)
        ok = np.isfinite(jac[:, j]) & np.isfinite(fd)
        assert ok.sum() > 100
        # Beams near a corner switch walls under the step; nearly all agree to 1e-5.
        assert np.mean(np.abs(fd[ok] - jac[ok, j]) < 1e-5) > 0.97


def test_four_normal_beams_in_a_square_room() -> None:
    # At the centre of a 4 m square, beams along the axes hit walls head on: each gives
    # d r / d (x, y) = -+ unit vector, so the xy block of I is diag(2, 2) / sigma^2, and
    # with no heading information among them the heading column is zero.
    world = Map.from_shapely(box(0.0, 0.0, 4.0, 4.0))
    angles = np.array([0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi])
    r, jac = range_jacobian(world, np.array([2.0, 2.0, 0.0]), angles, np.zeros(3), 10.0)
    np.testing.assert_allclose(r, 2.0)
    info = fisher_information(jac, 0.01)
    np.testing.assert_allclose(info[:2, :2], np.diag([2.0, 2.0]) / 0.01**2, atol=1e-6)
    np.testing.assert_allclose(info[2], 0.0, atol=1e-9)
    assert position_bound(info) == math.inf


def test_full_scan_bound_in_a_square_room() -> None:
    # From the centre of a square, the x-x entry of I has a closed form (below); the bound
    # scales with sigma.
    world = Map.from_shapely(box(-2.0, -2.0, 2.0, 2.0))
    n = 360
    pose = np.array([0.0, 0.0, 0.1])
    angles = -math.pi + 2 * math.pi / n * np.arange(n)
    r_true = cast_rays(world, pose[None], angles, 10.0)[0]
    scan = Scan.create(r_true, -math.pi, 2 * math.pi / n, 0.05, 10.0)
    b1 = scan_bound(world, pose, scan, 0.01)
    b2 = scan_bound(world, pose, scan, 0.02)
    assert b2 == pytest.approx(2 * b1, rel=1e-9)
    # A beam at heading phi that hits a wall x = +-a has d r / d x = -n_x / (n . v), squared
    # 1 / cos^2 phi; one that hits a wall y = +-a has d r / d x = 0. Beams more oblique than
    # 80 degrees are left out.
    phi = angles + pose[2]
    on_x_wall = np.abs(np.cos(phi)) >= np.abs(np.sin(phi))
    keep = on_x_wall & (np.abs(np.cos(phi)) >= math.cos(math.radians(80.0)))
    expected_xx = np.sum(1.0 / np.cos(phi[keep]) ** 2) / 0.01**2
    _, jac = range_jacobian(world, pose, angles, np.zeros(3), 10.0)
    info = fisher_information(jac, 0.01)
    assert info[0, 0] == pytest.approx(expected_xx, rel=1e-6)
    assert 0.0005 < b1 < 0.002


def test_people_and_dropouts_are_left_out() -> None:
    world = Map.from_shapely(box(-3.0, -2.0, 3.0, 2.0))
    n = 360
    pose = np.array([0.5, 0.2, 0.0])
    angles = -math.pi + 2 * math.pi / n * np.arange(n)
    clean = cast_rays(world, pose[None], angles, 10.0)[0]
    blocked = clean.copy()
    blocked[:60] = 0.5  # a person in front of 60 beams
    blocked[200:260] = np.nan  # dropouts
    with_people = Scan.create(blocked, -math.pi, 2 * math.pi / n, 0.05, 10.0)
    kept = clean.copy()
    kept[:60] = np.nan
    kept[200:260] = np.nan
    without = Scan.create(kept, -math.pi, 2 * math.pi / n, 0.05, 10.0)
    assert scan_bound(world, pose, with_people, 0.01) == pytest.approx(
        scan_bound(world, pose, without, 0.01), rel=1e-12
    )
