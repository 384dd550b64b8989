import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box
from shapely.ops import unary_union

from rlutf.map import Map
from rlutf.raycast import Beams, cast_rays


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
