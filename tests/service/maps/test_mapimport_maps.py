"""Import of the real map_server maps in bench/data/maps: area, rays, JSON, rendering."""

from __future__ import annotations

import io
import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from bench.scenarios import DATA
from rlutf.map import Map
from rlutf.raycast import cast_rays
from service.maps.mapimport import (
    ImportResult,
    MapImportError,
    import_grid,
    march_rays,
    render_map,
)

MAPS = DATA / "maps"
NAMES = ["depot", "tb3_sandbox"]


@cache
def imported(name: str, min_hole_area: float | None = None) -> ImportResult:
    if min_hole_area is None:
        return import_grid(MAPS / f"{name}.yaml")
    return import_grid(MAPS / f"{name}.yaml", min_hole_area=min_hole_area)


def clear_poses(free: np.ndarray, result: ImportResult, count: int, seed: int) -> np.ndarray:
    """Random poses in free cells at least three cells from any non-free cell."""
    clear = np.zeros_like(free)
    clear[3:-3, 3:-3] = sliding_window_view(free, (7, 7)).all(axis=(2, 3))
    rows, cols = np.nonzero(clear)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(rows), count, replace=False)
    grid = result.grid
    xy = grid.cell_centres(rows[pick], cols[pick])
    xy += rng.uniform(-0.5, 0.5, xy.shape) * grid.resolution
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, count)])


def agreement(result: ImportResult, free: np.ndarray, seed: int) -> float:
    """Share of beams whose polygon range is within two cells of the grid's range."""
    poses = clear_poses(result.polygons.free, result, 150, seed)
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    world = Map.from_geojson(result.map["geometry"])
    on_polygons = cast_rays(world, poses, angles, 40.0)
    on_grid = march_rays(result.grid, poses, angles, 40.0, free=free)
    diff = np.abs(on_polygons - on_grid)
    diff[np.isinf(on_polygons) & np.isinf(on_grid)] = 0.0
    return float(np.mean(diff <= 2.0 * result.grid.resolution))


@pytest.mark.parametrize("name", NAMES)
def test_area_matches_free_cells(name: str) -> None:
    everything = import_grid(
        MAPS / f"{name}.yaml", component="all", min_area=0.0, min_hole_area=0.0
    )
    grid = everything.grid
    cells_area = grid.free_cells * grid.cell_area
    assert everything.polygons.geometry.area == pytest.approx(cells_area, rel=0.02)
    default = imported(name)
    kept_area = float(default.polygons.free.sum()) * grid.cell_area
    assert default.polygons.geometry.area == pytest.approx(kept_area, rel=0.02)
    assert "polygons: area" in default.report[-1]


@pytest.mark.parametrize("name", NAMES)
def test_rays_agree_with_the_grid(name: str) -> None:
    # Tracing and simplification alone: every obstacle kept, compared with the raw grid.
    exact = imported(name, 0.0)
    assert agreement(exact, exact.grid.free, seed=1) >= 0.99
    # With the defaults, compared with the grid as imported (small specks filled).
    default = imported(name)
    assert agreement(default, default.polygons.free, seed=2) >= 0.99


@pytest.mark.parametrize("name", NAMES)
def test_map_is_valid_and_round_trips_through_json(name: str) -> None:
    result = imported(name)
    text = json.dumps(result.map)
    back = json.loads(text)
    assert back == result.map
    assert back["map_id"] == name
    assert back["frame_id"] == "map"
    world = Map.from_geojson(back["geometry"])
    assert world.geometry.is_valid
    assert world.geometry.equals_exact(result.polygons.geometry, 0.0)
    assert len(world.segments) == result.polygons.wall_count
    schemas = pytest.importorskip("schemas")
    assert schemas.decode(schemas.Map, text.encode(), max_bytes=10**7).map_id == name


def test_depot_report_lists_components() -> None:
    report = "\n".join(imported("depot").report)
    assert "grid: 604 x 307 cells of 0.05 m" in report
    assert "[0] " in report
    assert "kept (largest)" in report
    assert "dropped (not selected)" in report


def test_render_writes_a_png(tmp_path: Path) -> None:
    result = imported("tb3_sandbox")
    out = tmp_path / "tb3.png"
    render_map(result.map, out, poses=[[0.0, 0.0], [1.0, 0.5]])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    stream = io.BytesIO()
    render_map(result.polygons.geometry, stream, title="plain geometry")
    assert stream.getvalue()[:4] == b"\x89PNG"


def test_render_refuses_a_map_past_what_a_float_holds(tmp_path: Path) -> None:
    # finite corners at 1e308: drawn with shapely's and matplotlib's overflow warnings on the
    # terminal, a picture of nothing, exit 0
    huge = {"type": "Polygon", "coordinates": [[[0, 0], [1e308, 0], [0, 1e308], [0, 0]]]}
    with pytest.raises(MapImportError, match="more than a float holds"):
        render_map(huge, tmp_path / "h.png")
    assert not (tmp_path / "h.png").exists()
