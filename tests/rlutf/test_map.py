import math
import pickle

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon, box

from rlutf.errors import MapError
from rlutf.map import Map

ROOM = {
    "type": "Polygon",
    "coordinates": [
        [[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]],
        [[5, 5], [6, 5], [6, 6], [5, 6], [5, 5]],
    ],
}


def test_from_geojson_builds_walls_and_free_space() -> None:
    m = Map.from_geojson(ROOM)
    assert m.segments.shape == (8, 4)
    assert math.isclose(m.geometry.area, 199.0)
    inside = m.contains(np.array([[1.0, 1.0], [5.5, 5.5], [25.0, 1.0]]))
    assert inside.tolist() == [True, False, False]
    assert m.to_geojson()["type"] == "Polygon"


def test_multipolygon_is_accepted() -> None:
    m = Map.from_geojson(
        {
            "type": "MultiPolygon",
            "coordinates": [
                [[[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]]],
                [[[3, 0], [4, 0], [4, 1], [3, 1], [3, 0]]],
            ],
        }
    )
    assert len(m.segments) == 8


@pytest.mark.parametrize(
    ("geometry", "message"),
    [
        ({"type": "Point", "coordinates": [0, 0]}, "type"),
        ({"type": "Polygon", "coordinates": []}, "at least one ring"),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1], [0, 1]]]}, "not closed"),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [0, 0]]]}, "at least 4"),
        (
            {"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, float("nan")], [0, 0]]]},
            "non-finite",
        ),
        (
            {"type": "Polygon", "coordinates": [[[0, 0], [2, 2], [2, 0], [0, 2], [0, 0]]]},
            "Self-intersection",
        ),
        ({"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [2, 0], [0, 0]]]}, "invalid"),
    ],
)
def test_invalid_maps_say_what_and_where(geometry: dict, message: str) -> None:
    with pytest.raises(MapError, match=message):
        Map.from_geojson(geometry)


def test_empty_geometry_is_rejected() -> None:
    with pytest.raises(MapError, match="empty"):
        Map.from_shapely(Polygon())


def test_walls_near_is_a_superset_of_walls_in_range() -> None:
    rng = np.random.default_rng(0)
    holes = [box(x, y, x + 0.3, y + 0.3) for x, y in rng.uniform(1, 48, (60, 2))]
    geom = box(0, 0, 50, 50)
    for h in holes:
        geom = geom.difference(h)
    m = Map.from_shapely(geom)
    for x, y, r in [(10.0, 10.0, 3.0), (25.0, 40.0, 8.0), (49.0, 1.0, 2.0)]:
        near = set(m.index.walls_near(x, y, r).tolist())
        seg = m.segments
        # distance from (x, y) to each wall
        ax, ay, bx, by = seg.T
        ex, ey = bx - ax, by - ay
        u = np.clip(((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey), 0, 1)
        d = np.hypot(ax + u * ex - x, ay + u * ey - y)
        assert set(np.flatnonzero(d <= r).tolist()) <= near
        # and the index prunes: far fewer than all walls for a small radius
        if r <= 3.0:
            assert len(near) < len(seg) / 4


def test_walls_have_the_free_space_on_their_left() -> None:
    rng = np.random.default_rng(2)
    holes = [box(x, y, x + 0.5, y + 0.3) for x, y in rng.uniform(1, 8, (6, 2))]
    geom = box(0, 0, 10, 10)
    for h in holes:
        geom = geom.difference(h)
    # rings given clockwise (shell) and counter-clockwise (holes) are reoriented as well
    flipped = Polygon(geom.exterior.coords[::-1], [r.coords[::-1] for r in geom.interiors])
    for g in (geom, flipped):
        m = Map.from_shapely(g)
        ax, ay, bx, by = m.segments.T
        mid = np.column_stack([(ax + bx) / 2, (ay + by) / 2])
        left = np.column_stack([-(by - ay), bx - ax])
        left /= np.hypot(*left.T)[:, None]
        assert m.contains(mid + 1e-6 * left).all()
        assert not m.contains(mid - 1e-6 * left).any()
        np.testing.assert_allclose(m.wall_length, np.hypot(bx - ax, by - ay))


def test_contains_point_agrees_with_contains() -> None:
    m = Map.from_geojson(ROOM)
    points = np.array([[1.0, 1.0], [5.5, 5.5], [25.0, 1.0], [0.0, 3.0], [5.0, 5.5]])
    expected = m.contains(points).tolist()
    assert [m.contains_point(float(x), float(y)) for x, y in points] == expected


def test_limits_refuse_a_map_before_anything_is_built() -> None:
    from rlutf.map import MapLimits

    square = {
        "type": "Polygon",
        "coordinates": [[[0, 0], [2000, 0], [2000, 2000], [0, 2000], [0, 0]]],
    }
    with pytest.raises(MapError, match=r"2000 m x 2000 m = 4e\+06 m2.*max_map_area"):
        Map.from_geojson(square, limits=MapLimits(max_area=100_000.0))
    with pytest.raises(MapError, match="5 vertices, more than the limit of 4"):
        Map.from_geojson(square, limits=MapLimits(max_vertices=4))
    assert Map.from_geojson(square, limits=MapLimits(5e6, 5)).bounds == (0.0, 0.0, 2000.0, 2000.0)
    bad = {"type": "Polygon", "coordinates": [[[0, 0], [float("inf"), 0], [1, 1], [0, 0]]]}
    with pytest.raises(MapError, match="non-finite"):
        Map.from_geojson(bad, limits=MapLimits(max_area=1.0))


def test_finite_coordinates_whose_extent_overflows_are_refused() -> None:
    # Every coordinate finite, the area (or the width itself) past what a float holds: once let
    # through by the limit (its check skipped what was not finite) and then an OverflowError
    # in the wall index, an internal error for every robot placed on the map.
    from rlutf.map import MapLimits

    for corners in (
        [[0, 0], [1e308, 0], [0, 1e308], [0, 0]],
        [[-1e308, 0], [1e308, 0], [0, 1], [-1e308, 0]],
    ):
        geometry = {"type": "Polygon", "coordinates": [corners]}
        with pytest.raises(MapError, match=r"inf m2, more than the limit of 1e\+06 m2"):
            Map.from_geojson(geometry, limits=MapLimits(max_area=1e6))
        with pytest.raises(MapError, match="more than a float holds"):
            Map.from_geojson(geometry)


def test_the_wall_index_is_made_on_first_use() -> None:
    world = Map.from_geojson(
        {"type": "Polygon", "coordinates": [[[0, 0], [30, 0], [30, 20], [0, 20], [0, 0]]]}
    )
    assert "wall_index" not in world._derived  # a process that only validates pays nothing
    index = world.index
    assert (index.nx, index.ny) == (30, 20)
    assert world.index is index


def test_a_pickled_map_comes_back_the_same_without_what_is_made_on_first_use() -> None:
    m = Map.from_geojson(ROOM, cell_size=0.5)
    fresh = pickle.dumps(m)
    m.index  # noqa: B018 (made: not part of what is sent)
    sent = pickle.dumps(m)
    assert len(sent) == len(fresh)
    back = pickle.loads(sent)
    assert back.geometry.equals_exact(m.geometry, 0.0)
    assert np.array_equal(back.segments, m.segments)
    assert back.cell_size == 0.5
    assert np.array_equal(back.wall_start, m.wall_start)
    assert np.array_equal(back.wall_direction, m.wall_direction)
    assert np.array_equal(back.wall_length, m.wall_length)
    assert back.bounds == m.bounds
    points = np.array([[1.0, 1.0], [5.5, 5.5], [25.0, 1.0]])
    assert back.contains(points).tolist() == [True, False, False]
    assert back.contains_point(1.0, 1.0) and not back.contains_point(5.5, 5.5)
    assert shapely.is_prepared(back.geometry)  # as a map validated here
    assert "wall_index" not in back._derived
    assert np.array_equal(back.index.cell_walls, m.index.cell_walls)
