"""Map-change evidence: what one scan marks, grids merged in any order, persistent places."""

import math
from dataclasses import replace

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, Point, box

from rlutf.map import Map
from rlutf.mapchange import (
    ChangeGrid,
    ChangeSettings,
    Returns,
    _components,
    find_changes,
    map_walls,
)
from rlutf.sim import make_building

ROOM = Map.from_shapely(box(0.0, 0.0, 10.0, 6.0))
T0 = 1_700_000_000_000_000_000


def _returns(x: float, y: float, measured: np.ndarray, cast: np.ndarray) -> Returns:
    angles = np.linspace(-math.pi, math.pi, len(measured), endpoint=False)
    return Returns(
        np.array([x, y, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles), measured, cast
    )


def test_one_scan_marks_short_and_through_returns_where_they_disagree() -> None:
    grid = ChangeGrid(ROOM)
    # from (5, 3) beams point along -x, -y, +x and +y: the walls 5, 3, 5 and 3 m away
    cast = np.array([5.0, 3.0, 5.0, 3.0])
    measured = np.array([2.0, 3.01, 6.5, math.nan])  # short, fits, through, no return
    assert grid.add(_returns(5.0, 3.0, measured, cast), T0, "r1") == (1, 1)
    short, through = np.flatnonzero(grid.marks[0]), np.flatnonzero(grid.marks[1])
    assert len(short) == len(through) == 1
    assert Point(grid.centre(short)[0]).distance(Point(3.0, 3.0)) < 0.15
    assert Point(grid.centre(through)[0]).distance(Point(10.0, 3.0)) < 0.15  # at the wall
    assert grid.free.sum() > 0 and grid.scans == 1 and grid.robot_ids == {"r1"}
    assert (grid.first[0, short[0]], grid.last[0, short[0]]) == (T0, T0)


def _scans(count: int) -> list[tuple[Returns, int, str]]:
    rng = np.random.default_rng(3)
    out = []
    for k in range(count):
        cast = rng.uniform(1.0, 5.0, 90)
        measured = cast + rng.choice([0.0, -0.8, 0.6], 90, p=[0.8, 0.1, 0.1])
        pose = rng.uniform([2.0, 2.0], [8.0, 4.0])
        out.append((_returns(*pose, measured, cast), T0 + k * 700_000_000, f"r{k % 3}"))
    return out


def test_merged_grids_equal_one_grid_of_all_scans_in_any_order() -> None:
    scans = _scans(60)
    whole = ChangeGrid(ROOM)
    for r, stamp, robot in scans:
        whole.add(r, stamp, robot)
    parts = [ChangeGrid(ROOM) for _ in range(3)]
    for k, (r, stamp, robot) in enumerate(reversed(scans)):
        parts[k % 3].add(r, stamp, robot)
    for order in ([0, 1, 2], [2, 0, 1]):
        merged = ChangeGrid(ROOM)
        for i in order:
            merged.merge(parts[i])
        np.testing.assert_array_equal(merged.counts, whole.counts)
        np.testing.assert_array_equal(merged.times, whole.times)
        assert (merged.scans, merged.oldest_ns, merged.newest_ns, merged.robot_ids) == (
            whole.scans, whole.oldest_ns, whole.newest_ns, whole.robot_ids,
        )  # fmt: skip
    parts[0].clear()
    assert parts[0].counts.sum() == 0 and parts[0].scans == 0
    with pytest.raises(ValueError, match="merge"):
        whole.merge(ChangeGrid(Map.from_shapely(box(0.0, 0.0, 3.0, 3.0))))


def test_an_object_seen_over_time_is_reported_a_moment_is_not() -> None:
    settings = ChangeSettings()
    # a robot at (2, 3) looks along +x at a wall 8 m away; an object stands at x = 5
    cast = np.full(36, 8.0)
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), cast / np.cos(angles))  # fmt: skip
    brief, lasting = ChangeGrid(ROOM, settings), ChangeGrid(ROOM, settings)
    for k in range(30):  # 3 s: one moment
        brief.add(ret, T0 + k * 100_000_000, "r1")
    for k in range(30):  # the same scans spread over 30 s
        lasting.add(ret, T0 + k * 1_000_000_000, "r1")
    assert find_changes(brief) == []
    (change,) = find_changes(lasting)
    assert change.kind == "added" and change.geometry.distance(Point(5.0, 3.0)) < 0.3
    assert change.robots == 1 and 0.0 < change.confidence <= 1.0
    assert change.last_ns - change.first_ns == 29_000_000_000


def test_components_are_8_connected() -> None:
    nx = 10
    cells = np.array([0, 11, 22, 40, 41, 99])
    groups = _components(cells, nx)
    assert [g.tolist() for g in groups] == [[0, 11, 22], [40, 41], [99]]


def test_counts_saturate_rather_than_wrap_over_a_long_lived_map_version() -> None:
    """A map version lives for months and its grid only ever adds: a busy cell's int32 count
    passes 2^31 (a rack face that ten robots pass every minute, the cell a robot parks in with a
    fast lidar: days, not years). A sum that wrapped turned the count negative and the place
    vanished from the report (or a free count, negative, made a cell look occupied)."""
    top = np.iinfo(np.int32).max
    cast = np.full(36, 8.0)
    angles = np.linspace(-0.2, 0.2, 36)
    ret = Returns(np.array([2.0, 3.0, 0.0]), np.zeros(3), np.cos(angles), np.sin(angles),
                  3.0 / np.cos(angles), cast / np.cos(angles))  # fmt: skip
    seen = ChangeGrid(ROOM)
    for k in range(30):
        seen.add(ret, T0 + k * 1_000_000_000, "r1")
    part = seen.snapshot()
    # what another instance hands on, second after second: each payload within its limit
    busy = part.counts.copy()
    busy[0] = np.where(busy[0] > 0, 100_000_000, 0)
    merged = ChangeGrid(ROOM)
    for _ in range(25):  # 2.5e9 returns: past int32
        merged.merge(replace(part, counts=busy))
    assert merged.counts.min() >= 0
    assert merged.marks[0].max() == top
    merged.add(ret, T0 + 31_000_000_000, "r1")  # counted by the kernel: stays at the top
    assert merged.counts.min() >= 0 and merged.marks[0].max() == top
    (change,) = find_changes(merged)
    assert change.kind == "added" and change.geometry.distance(Point(5.0, 3.0)) < 0.3


#: A building of rooms and a room with two pillars: walls of several rings.
BUILDING = make_building(np.random.default_rng(5))
PILLARS = Map.from_shapely(
    box(0.0, 0.0, 10.0, 6.0).difference(box(2.0, 2.0, 3.0, 3.0)).difference(box(6.0, 1.0, 7.0, 4.0))
)


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from([ROOM, PILLARS, BUILDING]),
    st.lists(st.tuples(st.floats(-0.2, 1.2), st.floats(-0.2, 1.2)), min_size=0, max_size=40),
)
def test_the_walls_distance_equals_shapelys_to_the_boundary(world: Map, at: list) -> None:
    """The index of the walls is a fast path: the distances it gives are those to the whole
    boundary, bit for bit (a cell is kept or left out exactly as before)."""
    x0, y0, x1, y1 = world.bounds
    points = np.array([(x0 + u * (x1 - x0), y0 + v * (y1 - y0)) for u, v in at]).reshape(-1, 2)
    plain = shapely.distance(shapely.points(points), world.geometry.boundary)
    np.testing.assert_array_equal(map_walls(world).distance(points), plain)


def test_a_second_report_makes_no_walls_again_and_finds_the_same_changes() -> None:
    """The map's boundary (and the wall index over it) is made once per map version, kept with
    the map: it was made again for every report, tens of milliseconds for a map of real size."""
    world = Map.from_shapely(PILLARS.geometry)
    angles = np.linspace(-0.2, 0.2, 36)
    cos, sin = np.cos(angles), np.sin(angles)
    # from (4, 3) along +x: an object at x = 5.5 the map lacks (the pillar's face at 6 m) ...
    added = Returns(np.array([4.0, 3.0, 0.0]), np.zeros(3), cos, sin,
                    1.5 / cos, 2.0 / cos)  # fmt: skip
    # ... and from (8, 3) along +x, beams through the wall at x = 10
    removed = Returns(np.array([8.0, 3.0, 0.0]), np.zeros(3), cos, sin,
                      3.5 / cos, 2.0 / cos)  # fmt: skip
    grid = ChangeGrid(world)
    for k in range(30):
        grid.add(added, T0 + k * 1_000_000_000, "r1")
        grid.add(removed, T0 + k * 1_000_000_000, "r2")
    assert "mapchange:walls" not in world._derived
    first = find_changes(grid)
    walls = world._derived["mapchange:walls"]
    second = find_changes(grid)
    assert world._derived["mapchange:walls"] is walls  # not made again
    assert [c.kind for c in first] == ["added", "removed"]
    assert first[0].geometry.distance(Point(5.5, 3.0)) < 0.3
    assert first[1].geometry.within(LineString([(10.0, 0.0), (10.0, 6.0)]).buffer(1e-9))
    assert second == first  # the same changes, the same geometries
    # and those a map of the same walls, not yet used for a report, gives
    fresh = ChangeGrid(Map.from_shapely(PILLARS.geometry))
    fresh.merge(grid)
    assert find_changes(fresh) == first
