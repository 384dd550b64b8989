"""Grid to polygons: exact tracing, components, specks, origin yaw, and the wire Map dict."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from shapely.geometry import MultiPolygon, Polygon, box

from rlutf.map import Map
from service.maps.mapimport import (
    ComponentError,
    EmptyMapError,
    MapImportError,
    OccupancyGrid,
    grid_to_map,
    import_grid,
    map_id_from_name,
    parse_component,
    polygonize,
    trace_free_space,
)


def grid_of(
    free: np.ndarray, resolution: float = 0.1, origin: tuple[float, float, float] = (0, 0, 0)
) -> OccupancyGrid:
    free = np.asarray(free, dtype=bool)
    return OccupancyGrid(np.where(free, 0, 100).astype(np.int8), free, ~free, resolution, origin)


def rooms() -> np.ndarray:
    """Two rooms: a big one (30 x 20 cells) and a small one (8 x 6), rows bottom-up."""
    free = np.zeros((24, 50), dtype=bool)
    free[2:22, 2:32] = True
    free[5:11, 36:44] = True
    return free


@settings(max_examples=60, deadline=None)
@given(arrays(bool, st.tuples(st.integers(1, 14), st.integers(1, 14))))
def test_tracing_is_the_exact_union_of_free_cells(free: np.ndarray) -> None:
    if not free.any():
        with pytest.raises(EmptyMapError):
            trace_free_space(free, 0.5)
        return
    geom = trace_free_space(free, 0.5)
    assert geom.is_valid
    # Exact but for the pinches where free cells meet only at a corner (1e-3 cell each).
    assert geom.area == pytest.approx(free.sum() * 0.25, rel=2e-3)
    rows, cols = np.nonzero(free)
    centres = np.column_stack([cols + 0.5, rows + 0.5]) * 0.5
    assert shapely.contains_xy(geom, centres[:, 0], centres[:, 1]).all()
    rows, cols = np.nonzero(~free)
    assert not shapely.intersects_xy(geom, (cols + 0.5) * 0.5, (rows + 0.5) * 0.5).any()


def test_tracing_keeps_cell_corners_square() -> None:
    free = np.zeros((3, 4), dtype=bool)
    free[1, 1:3] = True
    geom = trace_free_space(free, 1.0)
    assert geom.equals(box(1.0, 1.0, 3.0, 2.0))
    assert geom.symmetric_difference(box(1.0, 1.0, 3.0, 2.0)).area == 0.0


def test_diagonal_neighbours_do_not_touch() -> None:
    free = np.array([[True, False], [False, True]])
    geom = trace_free_space(free, 1.0)
    assert isinstance(geom, MultiPolygon)
    assert len(geom.geoms) == 2
    assert geom.is_valid
    assert geom.geoms[0].distance(geom.geoms[1]) > 0


def test_largest_component_by_default_and_report_says_what_was_dropped() -> None:
    grid = grid_of(rooms())
    result = polygonize(grid)
    assert isinstance(result.geometry, Polygon)
    assert result.geometry.area == pytest.approx(6.0)
    assert [(c.cells, c.kept) for c in result.components] == [(600, True), (48, False)]
    lines = "\n".join(result.report(grid))
    assert "[0] 600 cells, 6.00 m2" in lines
    assert "kept (largest)" in lines
    assert "[1] 48 cells, 0.48 m2" in lines
    assert "dropped (not selected)" in lines


def test_component_by_index_point_or_all() -> None:
    grid = grid_of(rooms())
    assert polygonize(grid, component=1).geometry.area == pytest.approx(0.48)
    small = polygonize(grid, component=(4.0, 0.8))
    assert small.geometry.area == pytest.approx(0.48)
    assert small.components[1].reason == "contains point (4, 0.8)"
    both = polygonize(grid, component="all", min_area=0.1)
    assert isinstance(both.geometry, MultiPolygon)
    assert both.geometry.area == pytest.approx(6.48)
    big_only = polygonize(grid, component="all", min_area=1.0)
    assert big_only.geometry.area == pytest.approx(6.0)
    assert big_only.components[1].reason == "below min_area"
    point = polygonize(grid).components[1].point
    assert polygonize(grid, component=point).geometry.area == pytest.approx(0.48)
    assert 3.6 < point[0] < 4.4
    assert 0.5 < point[1] < 1.1


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        (2, "index 2 does not exist; the grid has 2 free component"),
        ((3.4, 0.5), r"point \(3.4, 0.5\) is in an occupied cell"),
        (
            (-1.0, 0.5),
            r"outside the grid, which spans x 0 to 5 m and y 0 to 2.4 m in the map frame",
        ),
    ],
)
def test_unknown_component_raises(spec: object, words: str) -> None:
    with pytest.raises(ComponentError, match=words):
        polygonize(grid_of(rooms()), component=spec)  # type: ignore[arg-type]


@pytest.mark.parametrize("text", ["nan,1", "1,inf", "-inf,0"])
def test_a_point_that_is_no_place_is_no_component(text: str) -> None:
    # --component nan,1 was taken for a point, and then contained in nothing
    with pytest.raises(MapImportError, match=r"a point like 12\.5,-3\.0"):
        parse_component(text)


def test_all_components_below_min_area_raises() -> None:
    with pytest.raises(EmptyMapError, match="at least 100 m2"):
        polygonize(grid_of(rooms()), component="all", min_area=100.0)


def test_specks_are_filled_and_obstacles_kept() -> None:
    free = np.zeros((40, 40), dtype=bool)
    free[1:-1, 1:-1] = True
    free[10, 10] = False  # a one-cell speck: 0.0025 m2 at 5 cm
    free[20:23, 20:23] = False  # a 3 x 3 pillar: 0.0225 m2
    grid = grid_of(free, resolution=0.05)
    result = polygonize(grid)
    assert isinstance(result.geometry, Polygon)
    assert len(result.geometry.interiors) == 1
    assert (result.holes_kept, result.holes_filled) == (1, 1)
    assert result.filled_area == pytest.approx(0.0025)
    kept = polygonize(grid, min_hole_area=0.0)
    assert len(kept.geometry.interiors) == 2
    assert kept.geometry.area == pytest.approx(grid.free_cells * grid.cell_area)
    assert "1 kept, 1 specks filled" in "\n".join(result.report(grid))


def test_simplify_tolerance_is_checked_and_bounds_the_change() -> None:
    yy, xx = np.mgrid[0:60, 0:60]
    free = (xx - 30) ** 2 + (yy - 30) ** 2 < 25**2  # a staircase disc
    grid = grid_of(free, resolution=0.05)
    exact = polygonize(grid, simplify=0.0).geometry
    simple = polygonize(grid).geometry
    assert shapely.get_num_coordinates(simple) < shapely.get_num_coordinates(exact) / 2
    assert shapely.hausdorff_distance(simple.exterior, exact.exterior) <= 0.025 + 1e-9
    assert simple.area == pytest.approx(exact.area, rel=0.01)
    for bad in (-0.01, 0.06, math.nan):
        with pytest.raises(MapImportError, match="simplify"):
            polygonize(grid, simplify=bad)


def test_no_free_space_raises() -> None:
    with pytest.raises(EmptyMapError, match="no free space"):
        polygonize(grid_of(np.zeros((5, 5), dtype=bool)))


def test_origin_yaw_rotates_about_the_lower_left_corner() -> None:
    # An L-shaped room (rows bottom-up), so any flip or wrong rotation changes the shape.
    free = np.zeros((12, 16), dtype=bool)
    free[1:11, 1:5] = True
    free[1:5, 5:15] = True
    x0, y0, yaw = 2.0, -1.0, 0.6
    grid = grid_of(free, resolution=0.25, origin=(x0, y0, yaw))
    geom = polygonize(grid, simplify=0.0).geometry
    local = Polygon(
        [(0.25, 0.25), (3.75, 0.25), (3.75, 1.25), (1.25, 1.25), (1.25, 2.75), (0.25, 2.75)]
    )
    expected = shapely.affinity.rotate(local, yaw, origin=(0.0, 0.0), use_radians=True)
    expected = shapely.affinity.translate(expected, x0, y0)
    assert geom.symmetric_difference(expected).area < 1e-9
    # The centre of cell (row 1, col 1) is (0.375, 0.375) in the grid frame.
    corner = np.array([x0, y0]) + 0.375 * np.array(
        [math.cos(yaw) - math.sin(yaw), math.sin(yaw) + math.cos(yaw)]
    )
    assert geom.contains(shapely.Point(*corner))


def test_import_grid_honours_yaw_from_yaml(tmp_path: Path) -> None:
    pixels = np.zeros((6, 8), dtype=np.uint8)
    pixels[1:5, 1:3] = 254  # image rows top-down: a tall free block on the left
    (tmp_path / "rot.pgm").write_bytes(b"P5\n8 6\n255\n" + pixels.tobytes())
    (tmp_path / "rot.yaml").write_text(
        "image: rot.pgm\nresolution: 1.0\norigin: [10.0, 5.0, 1.5707963267948966]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.25\n"
    )
    result = import_grid(tmp_path / "rot.yaml")
    # Grid frame: x in [1, 3], y in [1, 5]; rotated by 90 degrees: x in [-5, -1], y in [1, 3].
    expected = box(10.0 - 5.0, 5.0 + 1.0, 10.0 - 1.0, 5.0 + 3.0)
    assert Map.from_geojson(result.map["geometry"]).geometry.symmetric_difference(
        expected
    ).area == pytest.approx(0.0, abs=1e-9)
    assert result.map["map_id"] == "rot"
    assert result.report[0] == f"source: {tmp_path / 'rot.yaml'}"


def test_map_dict_is_wire_shaped_and_round_trips_through_json() -> None:
    free = rooms()
    free[8:10, 8:10] = False  # a pillar: a hole in the polygon
    result = grid_to_map(grid_of(free), map_id="two-rooms", version=4)
    wire = result.map
    assert set(wire) == {"map_id", "version", "frame_id", "geometry"}
    assert (wire["map_id"], wire["version"], wire["frame_id"]) == ("two-rooms", 4, "map")
    assert wire["geometry"]["type"] == "Polygon"
    assert len(wire["geometry"]["coordinates"]) == 2
    back = json.loads(json.dumps(wire))
    assert back == wire
    rebuilt = Map.from_geojson(back["geometry"]).geometry
    assert rebuilt.equals_exact(result.polygons.geometry, 0.0)
    assert rebuilt.exterior.is_ccw
    assert not rebuilt.interiors[0].is_ccw
    schemas = pytest.importorskip("schemas")
    model = schemas.decode(schemas.Map, json.dumps(wire).encode())
    assert model.map_id == "two-rooms"
    assert json.loads(schemas.encode(model)) == wire


def test_grid_to_map_checks_id_and_version() -> None:
    grid = grid_of(rooms())
    with pytest.raises(MapImportError, match="map_id"):
        grid_to_map(grid, map_id="bad id!")
    with pytest.raises(MapImportError, match="version"):
        grid_to_map(grid, map_id="ok", version=-1)


def test_cli_helpers() -> None:
    assert parse_component("all") == "all"
    assert parse_component(" 3 ") == 3
    assert parse_component("12.5,-3") == (12.5, -3.0)
    with pytest.raises(MapImportError, match="expected 'all', an index"):
        parse_component("largest")
    assert map_id_from_name("my map (v2).yaml") == "my-map-v2-yaml"
    with pytest.raises(MapImportError):
        map_id_from_name("???")


def test_each_components_point_is_its_cell_nearest_its_centroid(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Computed a band of rows at a time (a map of millions of cells took a GB whole): the same
    # cell as over the component at once, the first in row order among those as near.
    import importlib

    poly = importlib.import_module("service.maps.mapimport.polygonize")  # the module
    monkeypatch.setattr(poly, "_BAND_ROWS", 3)
    rng = np.random.default_rng(2)
    free = rng.random((40, 30)) < 0.55
    free[10:20, 4:12] = True  # one component of even sides: its centroid ties four cells
    labels = np.asarray(poly._label(free, connectivity=1), dtype=np.int64)
    n = int(labels.max())
    got = poly._points(labels, np.bincount(labels.ravel())[1:])
    for k in range(1, n + 1):
        cells = np.argwhere(labels == k)  # row order
        d = ((cells - cells.mean(axis=0)) ** 2).sum(axis=1)
        assert tuple(got[k]) == tuple(cells[np.argmin(d)]), k
