import math

import numpy as np
import shapely

from rlutf.field import DistanceField, WideSearch, distance_field, wide_search
from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan


def test_field_is_the_truncated_distance_to_the_walls() -> None:
    rng = np.random.default_rng(1)
    world = make_building(rng)
    field = DistanceField.of(world, resolution=0.1, truncation=0.5)
    height, width = field.values.shape
    rows = rng.integers(0, height, 400)
    cols = rng.integers(0, width, 400)
    x = field.origin[0] + (cols + 0.5) * field.resolution
    y = field.origin[1] + (rows + 0.5) * field.resolution
    exact = shapely.distance(world.geometry.boundary, shapely.points(x, y))
    np.testing.assert_allclose(field.values[rows, cols], np.minimum(exact, 0.5), atol=1e-5)
    far = field.at(np.array([[field.origin[0] - 5.0, 0.0]]))
    assert far[0] == 0.5


def test_the_field_is_made_once_per_map() -> None:
    world = make_building(np.random.default_rng(2))
    assert distance_field(world) is distance_field(world)


def test_wide_search_finds_the_pose_among_distinct_candidates() -> None:
    rng = np.random.default_rng(3)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(), rng)
    valid = scan.valid()
    a = scan.angles[valid]
    points = np.column_stack([scan.ranges[valid] * np.cos(a), scan.ranges[valid] * np.sin(a)])
    settings = WideSearch()
    centre = truth + np.array([0.3, -0.25, math.radians(12.0)])
    found, scored = wide_search(world, centre, points, 0.5, math.radians(15.0), settings)
    assert 1 <= len(found) <= settings.keep and scored > 1000
    scores = [s for _, s in found]
    assert scores == sorted(scores)
    best = found[0][0]
    assert math.hypot(*(best[:2] - truth[:2])) <= 1.5 * settings.step
    assert abs(best[2] - truth[2]) <= math.radians(3.0)
    for i, (p, _) in enumerate(found):
        for q, _ in found[:i]:
            apart = math.hypot(*(p[:2] - q[:2])) > 2 * settings.step + 1e-9
            assert apart or abs(p[2] - q[2]) > 1e-9


def test_wide_search_headings_are_bounded_for_far_points() -> None:
    # Issue 19: points 1e5 m away made the heading step a millionth of a radian.
    world = make_building(np.random.default_rng(3))
    centre = np.array([5.0, 5.0, 0.0])
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    far = 1e5 * np.column_stack([np.cos(angles), np.sin(angles)])
    settings = WideSearch(max_turns=64)
    _, scored = wide_search(world, centre, far, 0.2, math.radians(15.0), settings)
    offsets = scored // (2 * 64 + 1)
    assert scored == offsets * (2 * 64 + 1)
    near = 5.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    _, near_scored = wide_search(world, centre, near, 0.2, math.radians(15.0), settings)
    assert near_scored < scored  # near points: the usual step, fewer headings than the cap
