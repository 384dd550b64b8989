import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box
from shapely.ops import unary_union

from rlutf import region
from rlutf.map import Map
from rlutf.motion import compose
from rlutf.raycast import Beams, cast_rays
from rlutf.region import RegionCaster


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


def _region_poses(
    rng: np.random.Generator, centre: np.ndarray, radius: float, heading: float, k: int
) -> np.ndarray:
    r = radius * np.sqrt(rng.random(k))
    b = rng.uniform(0, 2 * math.pi, k)
    return centre + np.column_stack(
        [r * np.cos(b), r * np.sin(b), rng.uniform(-heading, heading, k)]
    )


@given(
    st.tuples(st.floats(0.1, 19.9), st.floats(0.1, 11.9), st.floats(-4, 4)),
    st.sampled_from([0.0, 0.02, 0.3, 2.0]),
    st.sampled_from([0.0, 0.01, 0.2]),
    st.sampled_from([3.0, 12.0]),
    st.sampled_from([(0.0, 0.0, 0.0), (0.25, -0.1, 0.4)]),
    st.integers(8, 90),
    st.integers(0, 2**31),
)
@settings(max_examples=40, deadline=None)
def test_region_caster_matches_brute_force(
    centre: tuple, radius: float, heading: float, max_range: float, offset: tuple, n: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    angles = np.linspace(-math.pi, math.pi, n, endpoint=False) + rng.uniform(-0.1, 0.1)
    beams = Beams.of(angles)
    off = np.array(offset)
    caster = RegionCaster(WORLD, beams, centre, radius, heading, max_range, off)
    middle = np.array(centre)
    poses = np.vstack([middle[None], _region_poses(rng, middle, radius, heading, 6)])
    # exact for every pose of the region whose sensor is in the free space
    sensors = compose(poses, off)
    poses = poses[WORLD.contains(sensors[:, :2])]
    if len(poses) == 0:
        return
    got = caster.cast(poses)
    ref = np.minimum(brute_force(WORLD, compose(poses, off), angles, max_range), max_range)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_region_caster_poses_inside_means_the_disc_is_free() -> None:
    rng = np.random.default_rng(3)
    beams = Beams.of(np.linspace(-math.pi, math.pi, 36, endpoint=False))
    claimed = 0
    for _ in range(200):
        centre = np.array([*rng.uniform((0.2, 0.2), (19.8, 11.8)), 0.0])
        radius = float(rng.choice([0.05, 0.5, 1.5]))
        caster = RegionCaster(WORLD, beams, centre, radius, 0.0, 5.0)
        if caster.poses_inside:
            claimed += 1
            disc = _region_poses(rng, centre, radius, 0.0, 50)
            assert WORLD.contains(disc[:, :2]).all()
        else:
            inside = WORLD.contains(centre[None, :2])[0]
            clearance = WORLD.geometry.boundary.distance(Point(centre[0], centre[1]))
            assert not inside or clearance <= radius + 1e-9
    assert claimed > 50


def test_region_caster_with_one_pose_equals_cast_rays() -> None:
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    beams = Beams.of(angles)
    pose = np.array([4.0, 6.0, 0.7])
    got = RegionCaster(WORLD, beams, pose, 0.0, 0.0, 8.0).cast(pose[None])
    ref = cast_rays(WORLD, pose, beams, 8.0)
    np.testing.assert_allclose(got, np.minimum(ref, 8.0), atol=1e-9)
    # fewer pairs than (walls x beams): only walls facing the region, only their beams
    caster = RegionCaster(WORLD, beams, pose, 0.0, 0.0, 8.0)
    assert caster.pairs < 3 * len(angles)


def test_selected_beams_cast_like_fresh_beams() -> None:
    angles = np.random.default_rng(5).uniform(-4, 4, 80)
    keep = np.random.default_rng(6).random(80) < 0.7
    p = np.array([[3.0, 3.0, 0.3], [10.0, 6.0, -2.0]])
    picked = Beams.of(angles).select(keep)
    np.testing.assert_array_equal(picked.angles, angles[keep])
    np.testing.assert_array_equal(
        cast_rays(WORLD, p, picked, 12.0), cast_rays(WORLD, p, Beams.of(angles[keep]), 12.0)
    )
    everything = Beams.of(angles)
    assert everything.select(np.ones(80, dtype=bool)) is everything


@pytest.mark.parametrize("first_ring", [0.5, 2.0])
def test_region_caster_rings_skip_hidden_walls_exactly(
    monkeypatch: pytest.MonkeyPatch, first_ring: float
) -> None:
    # Force the ring-by-ring path of large maps on the small test map.
    monkeypatch.setattr(region, "_RING_WALLS", 0)
    monkeypatch.setattr(region, "_FIRST_RING", first_ring)
    rng = np.random.default_rng(11)
    angles = np.linspace(-math.pi, math.pi, 120, endpoint=False)
    beams = Beams.of(angles)
    culled = 0
    for trial in range(60):
        centre = np.array([*rng.uniform((0.3, 0.3), (19.7, 11.7)), rng.uniform(-3, 3)])
        if not WORLD.contains(centre[None, :2])[0]:
            continue
        radius, heading = [(0.0, 0.0), (0.03, 0.01), (0.2, 0.05)][trial % 3]
        off = np.array([(0.0, 0.0, 0.0), (0.15, 0.05, -0.2)][trial % 2])
        caster = RegionCaster(WORLD, beams, centre, radius, heading, 30.0, off)
        poses = np.vstack([centre[None], _region_poses(rng, centre, radius, heading, 4)])
        poses = poses[WORLD.contains(compose(poses, off)[:, :2])]
        ref = np.minimum(brute_force(WORLD, compose(poses, off), angles, 30.0), 30.0)
        np.testing.assert_allclose(caster.cast(poses), ref, rtol=0, atol=1e-9)
        # Against one window of walls without culling (which skips them the same way).
        with monkeypatch.context() as m:
            m.setattr(region, "_RING_WALLS", 10**9)
            m.setattr(region._Region, "cull", lambda self, beam, wall, *rest: (beam, wall))
            full = RegionCaster(WORLD, beams, centre, radius, heading, 30.0, off)
        culled += caster.pairs < full.pairs
    assert culled > 10  # the rings did skip walls behind certain hits


def test_selecting_no_beams_gives_empty_beams() -> None:
    beams = Beams.of(np.linspace(-math.pi, math.pi, 12, endpoint=False))
    none = beams.select(np.zeros(12, dtype=bool))
    assert len(none) == 0 and len(none.order) == 0 and len(none.sorted_wrapped) == 0


def test_culling_drops_hidden_pairs_without_changing_ranges(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(21)
    angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    beams = Beams.of(angles)
    culled = 0
    for trial in range(40):
        centre = np.array([*rng.uniform((0.3, 0.3), (19.7, 11.7)), rng.uniform(-3, 3)])
        if not WORLD.contains(centre[None, :2])[0]:
            continue
        radius, heading = [(0.0, 0.0), (0.02, 0.01), (0.3, 0.1)][trial % 3]
        off = np.array([(0.0, 0.0, 0.0), (0.2, -0.1, 0.3)][trial % 2])
        poses = np.vstack([centre[None], _region_poses(rng, centre, radius, heading, 5)])
        poses = poses[WORLD.contains(compose(poses, off)[:, :2])]
        caster = RegionCaster(WORLD, beams, centre, radius, heading, 30.0, off)
        with monkeypatch.context() as m:
            m.setattr(region._Region, "cull", lambda self, beam, wall, *rest: (beam, wall))
            full = RegionCaster(WORLD, beams, centre, radius, heading, 30.0, off)
        assert caster.pairs <= full.pairs
        culled += caster.pairs < full.pairs
        # The pairs dropped are never a first hit: the very same ranges, bit for bit.
        np.testing.assert_array_equal(caster.cast(poses), full.cast(poses))
        ref = np.minimum(brute_force(WORLD, compose(poses, off), angles, 30.0), 30.0)
        np.testing.assert_allclose(caster.cast(poses), ref, rtol=0, atol=1e-9)
    assert culled > 10


def test_region_caster_with_no_pairs_gives_max_range(recwarn: pytest.WarningsRecorder) -> None:
    beams = Beams.of(np.linspace(-math.pi, math.pi, 36, endpoint=False))
    centre = np.array([10.0, 6.0, 0.3])
    # No wall anywhere near a point 2.5 m from every wall: no pair at all.
    caster = RegionCaster(WORLD, beams, centre, 0.01, 0.01, 0.05)
    assert caster.pairs == 0
    poses = np.vstack([centre, centre + np.array([0.005, 0.0, 0.005])])
    np.testing.assert_array_equal(caster.cast(poses), np.full((2, 36), 0.05))
    assert caster.cast(np.zeros((0, 3))).shape == (0, 36)
    assert not recwarn.list


def test_region_caster_where_every_pose_misses_every_wall(
    recwarn: pytest.WarningsRecorder,
) -> None:
    # Pairs exist (walls within reach of the region's window) but no beam reaches them.
    beams = Beams.of(np.linspace(-math.pi, math.pi, 72, endpoint=False))
    centre = np.array([10.0, 6.0, 0.0])
    caster = RegionCaster(WORLD, beams, centre, 0.2, 0.1, 2.2)
    assert caster.pairs > 0
    poses = np.array([[10.0, 6.0, 0.0], [10.1, 6.05, 0.05], [9.9, 5.95, -0.05]])
    ref = np.minimum(brute_force(WORLD, poses, beams.angles, 2.2), 2.2)
    assert np.all(ref == 2.2)
    np.testing.assert_array_equal(caster.cast(poses), ref)
    assert not recwarn.list
