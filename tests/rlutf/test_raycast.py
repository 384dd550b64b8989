import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box
from shapely.ops import unary_union

from rlutf.map import Map
from rlutf.raycast import Beams, cast_rays, cast_with_walls


def brute_force(world: Map, poses: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
    out = np.full((len(poses), len(angles)), np.inf)
    for k, (x, y, th) in enumerate(poses):
        for j, a in enumerate(angles):
            dx, dy = math.cos(th + a), math.sin(th + a)
            for ax, ay, bx, by in world.segments:
                ex, ey = bx - ax, by - ay
                den = dx * ey - dy * ex
                if den == 0:
                    continue
                px, py = ax - x, ay - y
                with np.errstate(over="ignore"):  # a ray all but parallel: t, s infinite, no hit
                    t = (px * ey - py * ex) / den
                    s = (px * dy - py * dx) / den
                if 0 <= t <= max_range and 0 <= s <= 1:
                    out[k, j] = min(out[k, j], t)
    return out


def _world() -> Map:
    rng = np.random.default_rng(1)
    holes = [Point(*rng.uniform((2, 2), (18, 10))).buffer(0.5, quad_segs=2) for _ in range(10)]
    return Map.from_shapely(box(0, 0, 20, 12).difference(unary_union(holes)))


WORLD = _world()


@given(
    st.lists(
        st.tuples(st.floats(0.1, 19.9), st.floats(0.1, 11.9), st.floats(-4, 4)),
        min_size=1,
        max_size=3,
    ),
    st.sampled_from([3.0, 8.0, 30.0]),
    st.integers(8, 72),
    st.booleans(),
)
@settings(max_examples=25, deadline=None)
def test_matches_brute_force(poses: list, max_range: float, n: int, uniform: bool) -> None:
    p = np.array(poses)
    angles = (
        np.linspace(-math.pi, math.pi, n, endpoint=False)
        if uniform
        else np.random.default_rng(n).uniform(-4, 4, n)
    )
    got = cast_rays(WORLD, p, angles, max_range)
    ref = brute_force(WORLD, p, angles, max_range)
    assert np.array_equal(np.isinf(got), np.isinf(ref))
    np.testing.assert_allclose(got[np.isfinite(got)], ref[np.isfinite(ref)], atol=1e-9)
    # hits never beyond max range
    assert np.all(got[np.isfinite(got)] <= max_range)


def test_known_ranges_in_a_box() -> None:
    m = Map.from_shapely(box(0, 0, 10, 4))
    r = cast_rays(m, [2.0, 1.0, 0.0], [0.0, math.pi / 2, math.pi, -math.pi / 2], 20.0)
    np.testing.assert_allclose(r[0], [8.0, 3.0, 2.0, 1.0], atol=1e-12)
    far = cast_rays(m, [2.0, 1.0, 0.0], [0.0], 5.0)
    assert np.isinf(far[0, 0])


def test_prepared_beams_give_the_same_result() -> None:
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    p = np.array([[3.0, 3.0, 0.3], [10.0, 6.0, -2.0]])
    np.testing.assert_array_equal(
        cast_rays(WORLD, p, angles, 12.0), cast_rays(WORLD, p, Beams.of(angles), 12.0)
    )


def test_empty_inputs() -> None:
    assert cast_rays(WORLD, np.zeros((0, 3)), [0.0, 1.0], 5.0).shape == (0, 2)
    assert cast_rays(WORLD, [1.0, 1.0, 0.0], [], 5.0).shape == (1, 0)


def test_selected_beams_cast_like_fresh_beams() -> None:
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    keep = np.random.default_rng(4).random(90) < 0.6
    p = np.array([[5.0, 5.0, 0.4]])
    picked = Beams.of(angles).select(keep)
    np.testing.assert_array_equal(
        cast_rays(WORLD, p, picked, 12.0), cast_rays(WORLD, p, Beams.of(angles[keep]), 12.0)
    )
    assert len(Beams.of(angles).select(np.zeros(90, dtype=bool))) == 0


def test_hit_walls_are_the_walls_hit() -> None:
    rng = np.random.default_rng(7)
    angles = np.linspace(-math.pi, math.pi, 120, endpoint=False)
    for _ in range(5):
        x, y = rng.uniform((0.2, 0.2), (19.8, 11.8))
        if not WORLD.contains_point(x, y):
            continue
        pose = np.array([x, y, rng.uniform(-3, 3)])
        ranges, walls = cast_with_walls(WORLD, pose, angles, 30.0)
        hit = walls[0] >= 0
        assert hit.any()
        assert np.all(np.isfinite(ranges[0][hit])) and np.all(np.isinf(ranges[0][~hit]))
        # Each hit point lies on the wall named for it.
        pts = pose[:2] + ranges[0][hit, None] * np.column_stack(
            [np.cos(pose[2] + angles[hit]), np.sin(pose[2] + angles[hit])]
        )
        seg = WORLD.segments[walls[0][hit]]
        a, d = seg[:, :2], seg[:, 2:] - seg[:, :2]
        cross = d[:, 0] * (pts[:, 1] - a[:, 1]) - d[:, 1] * (pts[:, 0] - a[:, 0])
        np.testing.assert_allclose(cross / np.hypot(d[:, 0], d[:, 1]), 0.0, atol=1e-9)


def test_rays_from_outside_the_map_box_enter_it() -> None:
    angles = np.array([0.0, math.pi / 2, math.pi])
    got = cast_rays(WORLD, np.array([-5.0, 6.0, 0.0]), angles, 100.0)[0]
    want = brute_force(WORLD, np.array([[-5.0, 6.0, 0.0]]), angles, 100.0)[0]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert got[0] == pytest.approx(5.0) and np.isinf(got[1]) and np.isinf(got[2])
