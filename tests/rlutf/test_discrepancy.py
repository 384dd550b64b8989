import math

import numpy as np
import shapely

from rlutf.discrepancy import PolarArea, anchored_turning, polar_area, turning_steps


def _star(ranges: np.ndarray, angles: np.ndarray) -> np.ndarray:
    return np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])


ANGLES = np.linspace(-math.pi, math.pi, 180, endpoint=False)


def _box_ranges(cx: float, cy: float, heading: float = 0.0) -> np.ndarray:
    # ranges from (cx, cy) inside the box [0, 4] x [0, 3] along ANGLES + heading
    d = np.column_stack([np.cos(ANGLES + heading), np.sin(ANGLES + heading)])
    with np.errstate(divide="ignore"):
        tx = np.where(d[:, 0] > 0, (4 - cx) / d[:, 0], np.where(d[:, 0] < 0, -cx / d[:, 0], np.inf))
        ty = np.where(d[:, 1] > 0, (3 - cy) / d[:, 1], np.where(d[:, 1] < 0, -cy / d[:, 1], np.inf))
    return np.minimum(tx, ty)


def test_identical_polygons_have_zero_discrepancy() -> None:
    r = _box_ranges(1.0, 1.0)
    ring = _star(r, ANGLES)
    assert anchored_turning(turning_steps(ring), turning_steps(ring))[0] < 1e-9
    assert polar_area(r[None], r, ANGLES, closing=False)[0] == 0.0


def test_polar_area_agrees_with_polygon_symmetric_difference() -> None:
    real = _box_ranges(1.0, 1.0)
    virt = _box_ranges(1.2, 0.9)
    pr = shapely.polygons(_star(real, ANGLES))
    pv = shapely.polygons(_star(virt, ANGLES))
    exact = shapely.area(shapely.symmetric_difference(pv, pr)) / shapely.length(pr)
    approx = polar_area(virt[None], real, ANGLES, closing=False)[0]
    assert abs(approx - exact) / exact < 0.1


def test_discrepancies_grow_with_pose_error() -> None:
    real = _box_ranges(2.0, 1.5)
    offsets = [0.0, 0.05, 0.2, 0.5]
    virt = np.array([_box_ranges(2.0 + o, 1.5) for o in offsets])
    area = polar_area(virt, real, ANGLES, closing=False)
    assert np.all(np.diff(area) > 0)
    steps_v = turning_steps(np.array([_star(v, ANGLES) for v in virt]))
    turning = anchored_turning(steps_v, turning_steps(_star(real, ANGLES)))
    # The anchored turning function is zero only at the true pose; it is not monotonic in the
    # error (a shifted corner moves every later breakpoint), which the benchmarks show.
    assert turning[0] < 1e-9 and np.all(turning[1:] > 0.01)


def test_turning_sees_heading() -> None:
    real = _box_ranges(2.0, 1.5)
    turned = _box_ranges(2.0, 1.5, heading=0.05)
    d = anchored_turning(turning_steps(_star(turned, ANGLES)), turning_steps(_star(real, ANGLES)))
    assert d[0] > 0.01
    norm = anchored_turning(
        turning_steps(_star(turned, ANGLES)), turning_steps(_star(real, ANGLES)), normalise=True
    )
    assert norm[0] > 0.01


def test_prepared_area_equals_polar_area() -> None:
    rng = np.random.default_rng(0)
    real = _box_ranges(1.3, 1.1)
    virt = np.array([_box_ranges(1.3 + dx, 1.1 + dy) for dx, dy in rng.normal(0, 0.05, (5, 2))])
    for closing in (False, True):
        prepared = PolarArea(real, ANGLES, closing)
        np.testing.assert_allclose(prepared(virt), polar_area(virt, real, ANGLES, closing))
        with_hints = PolarArea(
            real, ANGLES, closing, unit=np.exp(1j * ANGLES), gaps=np.abs(np.diff(ANGLES))
        )
        np.testing.assert_allclose(with_hints(virt), prepared(virt), rtol=1e-12)


def test_capped_area_bounds_each_beam() -> None:
    real = _box_ranges(2.0, 1.5)
    near = _box_ranges(2.01, 1.5)
    # one beam that jumps far away (an edge grazed, or a person in the real scan)
    jump = near.copy()
    jump[40] += 5.0
    exact = polar_area(np.array([near, jump]), real, ANGLES, closing=False)
    capped = polar_area(np.array([near, jump]), real, ANGLES, closing=False, cap=0.1)
    # small errors are untouched by the cap ...
    assert capped[0] == exact[0]
    # ... and the jump costs at most a band of cap width along that beam's sectors
    perimeter = 14.0
    bound = 0.1 * real[40] * (ANGLES[1] - ANGLES[0]) / perimeter
    assert exact[1] - exact[0] > 10 * bound
    assert capped[1] - capped[0] <= bound * 1.01
    assert np.all(capped <= exact)
