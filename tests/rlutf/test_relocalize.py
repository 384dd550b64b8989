import math

import numpy as np
import pytest
import shapely
import shapely.affinity
from shapely.geometry import box

from rlutf import _bnb
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.map import Map
from rlutf.motion import relative, wrap_angle
from rlutf.relocalize import RelocalizeSettings, relocalize, search_grid
from rlutf.sim import LidarModel, make_building, make_trajectory, random_free_point, simulate_scan


def _close(pose: np.ndarray, truth: np.ndarray, metres: float, degrees: float) -> bool:
    turn = abs(float(wrap_angle(pose[2] - truth[2])))
    return math.hypot(*(pose[:2] - truth[:2])) < metres and turn < math.radians(degrees)


def test_branch_and_bound_equals_brute_force_on_the_grid() -> None:
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, (40, 50)).astype(np.uint8)
    free = (rng.random((40, 50)) < 0.7).astype(np.uint8)
    depth = 4
    levels, valid = _bnb.pyramid(base, depth), _bnb.pyramid(free, depth)
    # level k is the maximum over the window of 2^k cells that starts at the cell
    assert levels[2, 5, 7] == base[5:9, 7:11].max()
    cx = rng.integers(-12, 12, (6, 15))
    cy = rng.integers(-12, 12, (6, 15))
    totals, rots, cols, rows, _ = _bnb.search(
        levels, valid, cx, cy, np.array([0.0, 0.0, -1.0]), 0, 1, 1, 1
    )
    best = -1
    where = None
    for r in range(6):
        for j in range(40):
            for i in range(50):
                if not free[j, i]:
                    continue
                c, w = i + cx[r], j + cy[r]
                ok = (c >= 0) & (c < 50) & (w >= 0) & (w < 40)
                total = int(base[w[ok], c[ok]].astype(np.int64).sum())
                if total > best:
                    best, where = total, (r, i, j)
    assert totals[0] == best
    r, i, j = rots[0], cols[0], rows[0]
    c, w = i + cx[r], j + cy[r]
    ok = (c >= 0) & (c < 50) & (w >= 0) & (w < 40)
    assert int(base[w[ok], c[ok]].astype(np.int64).sum()) == best and where is not None


def test_a_nodes_bound_is_the_same_inside_the_grid_and_at_its_edges() -> None:
    """A node whose points all fall inside the grid is summed without edge checks; its bound is
    the one the checked sum gives, and a node at an edge still reads the edge's windows."""
    rng = np.random.default_rng(5)
    level = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    cx, cy = rng.integers(-10, 11, 30), rng.integers(-7, 8, 30)
    extent = np.array([cx.min(), cx.max(), cy.min(), cy.max()])
    wide = np.array([-(10**6), 10**6, -(10**6), 10**6])  # never inside: always the checked sum
    for i, j in ((40, 30), (10, 7), (69, 52), (0, 0), (-4, 3), (75, 58)):
        assert _bnb._bound(level, cx, cy, i, j, 4, extent) == _bnb._bound(
            level, cx, cy, i, j, 4, wide
        ), (i, j)
    inside = int(level[30 + cy, 40 + cx].astype(np.int64).sum())
    assert _bnb._bound(level, cx, cy, 40, 30, 4, extent) == inside


def test_top_nodes_are_taken_from_the_highest_bound_down_in_index_order_among_equals() -> None:
    """The counting sort of the top nodes gives the order a stable sort of the negated bounds
    gives (which nodes are explored first decides which of equal leaves is kept)."""
    rng = np.random.default_rng(4)
    for count, high in ((0, 5), (1, 5), (300, 3), (5000, 30_600)):
        bounds = rng.integers(0, high + 1, count + 9).astype(np.int32)  # past count: not read
        expected = np.argsort(-bounds[:count], kind="stable")
        assert np.array_equal(_bnb._by_bound(bounds, count), expected), count


@pytest.mark.parametrize("seed", [2, 3])
def test_one_scan_finds_the_robot_anywhere(seed: int) -> None:
    rng = np.random.default_rng(seed)
    world = make_building(rng, 30.0, 16.0, 4, 2)
    right = 0
    for _ in range(8):
        p = random_free_point(world, rng, 0.3)
        truth = np.array([p[0], p[1], rng.uniform(-math.pi, math.pi)])
        result = relocalize(world, simulate_scan(world, truth, LidarModel(), rng))
        best = result.best
        assert best is not None
        if result.found and not result.ambiguous:
            # never confidently wrong
            assert _close(best.pose, truth, 0.05, 1.0), (best.pose, truth)
            right += 1
        else:
            assert any(_close(h.pose, truth, 0.1, 2.0) for h in result.hypotheses)
    assert right >= 7


def test_identical_rooms_are_ambiguous_and_hold_the_truth() -> None:
    room = box(0.0, 0.0, 6.0, 4.0).difference(box(1.0, 1.0, 1.6, 1.6))
    twin = shapely.affinity.translate(room, 10.0, 0.0)
    world = Map.from_shapely(shapely.MultiPolygon([room, twin]))
    truth = np.array([3.5, 2.5, 0.4])
    result = relocalize(world, simulate_scan(world, truth, LidarModel(), np.random.default_rng(4)))
    assert result.ambiguous
    assert len(result.hypotheses) >= 2
    assert any(_close(h.pose, truth, 0.05, 1.0) for h in result.hypotheses)
    twin_pose = truth + np.array([10.0, 0.0, 0.0])
    assert any(_close(h.pose, twin_pose, 0.05, 1.0) for h in result.hypotheses)
    # A region around one of them decides it.
    near = relocalize(
        world,
        simulate_scan(world, truth, LidarModel(), np.random.default_rng(4)),
        region=(3.0, 2.0, 2.5),
    )
    assert near.found and not near.ambiguous and near.best is not None
    assert _close(near.best.pose, truth, 0.05, 1.0)


def test_the_search_grid_is_made_once_per_map() -> None:
    world = make_building(np.random.default_rng(5))
    cfg = RelocalizeSettings()
    grid = search_grid(world, cfg)
    assert search_grid(world, cfg) is grid
    assert grid.levels.shape[0] == cfg.depth and grid.nbytes > 0


def test_a_kidnapped_robot_comes_back_without_a_confident_wrong_pose() -> None:
    rng = np.random.default_rng(6)
    world = make_building(rng, 30.0, 16.0, 4, 2)
    before, after = make_trajectory(world, rng, 20), make_trajectory(world, rng, 30)
    truth = np.vstack([before, after])
    loc = Localizer(world, truth[0], spread=(0.0, 0.0))
    back = None
    for k in range(1, len(truth)):
        # carried away at scan 20: the odometry says it did not move
        motion = np.zeros(3) if k == 20 else relative(truth[k - 1], truth[k])
        res = loc.update(motion, simulate_scan(world, truth[k], LidarModel(), rng))
        if k < 20:
            continue
        if res.status != "lost":
            assert _close(res.pose, truth[k], 0.05, 1.0), (k, res.status, res.pose, truth[k])
            back = k - 20 if back is None else back
    assert back is not None and back <= 10


def test_relocalize_on_request_and_bad_regions() -> None:
    rng = np.random.default_rng(7)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 3)
    loc = Localizer(world, np.zeros(3))
    loc.relocalize()
    assert loc.relocalizing
    res = loc.update(np.zeros(3), simulate_scan(world, truth[1], LidarModel(), rng))
    assert res.relocalizing and res.status == "corrected" and not res.hypotheses
    assert _close(res.pose, truth[1], 0.05, 1.0)
    nxt = loc.update(
        relative(truth[1], truth[2]), simulate_scan(world, truth[2], LidarModel(), rng)
    )
    assert not nxt.relocalizing and nxt.status != "lost"
    for bad in ((1.0, 2.0, 0.0), (math.nan, 0.0, 1.0), (0.0, 0.0, -3.0)):
        with pytest.raises(ValueError, match="region"):
            loc.relocalize(bad)


def test_hypotheses_headings_are_wrapped() -> None:
    room = box(0.0, 0.0, 6.0, 4.0).difference(box(1.0, 1.0, 1.6, 1.6))
    twin = shapely.affinity.translate(room, 10.0, 0.0)
    world = Map.from_shapely(shapely.MultiPolygon([room, twin]))
    truth = np.array([3.5, 2.5, math.pi - 0.001])
    result = relocalize(world, simulate_scan(world, truth, LidarModel(), np.random.default_rng(8)))
    assert result.hypotheses
    for h in result.hypotheses:
        assert -math.pi <= h.pose[2] < math.pi


def test_a_circle_the_robot_is_not_in_gives_way_to_the_whole_map() -> None:
    """An operator's circle (`rlutf relocalize --near`) that misses the robot was searched for
    good: the robot stayed lost, or after hundreds of scans took a place in the circle that
    happened to look like its own. After ``relocalize_after`` scans without an answer the
    whole map is searched."""
    rng = np.random.default_rng(41)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 40)
    scans = [simulate_scan(world, truth[i], LidarModel(), rng) for i in range(40)]
    x0, y0, x1, y1 = world.bounds
    # the corner of the building farthest from the robot, a circle of 1 m
    far = max(((x0, y0), (x0, y1), (x1, y0), (x1, y1)), key=lambda c: math.dist(c, truth[0, :2]))
    region = (far[0], far[1], 1.0)
    assert math.dist(far, truth[0, :2]) > 5.0
    loc = Localizer(world, truth[0])
    loc.relocalize(region)
    assert loc.searched_region == region
    found = None
    for i in range(1, 40):
        res = loc.update(relative(truth[i - 1], truth[i]), scans[i])
        if res.status != "lost":
            found = i
            break
    assert found is not None and found <= loc.config.relocalize_after + 3, found
    assert _close(res.pose, truth[found], 0.05, 1.0)
    assert loc.searched_region is None and not loc.relocalizing
    # Kept to the circle (relocalize_after 0: the localizer never gives it up), it stays lost.
    kept = Localizer(world, truth[0], LocalizerConfig(relocalize_after=0))
    kept.relocalize(region)
    statuses = {
        kept.update(relative(truth[i - 1], truth[i]), scans[i]).status for i in range(1, 20)
    }
    assert statuses == {"lost"} and kept.searched_region == region
