"""The wall fit of the even/odd trial: traced walls moved onto the hit points they stand for."""

from __future__ import annotations

import numpy as np
import shapely
import shapely.affinity
from shapely.geometry import Polygon, box

from bench.wallfit import WallFit, fit_walls
from rlutf.map import Map, geometry_from_geojson
from rlutf.raycast import cast_rays
from service.maps.mapimport import build_grid, grid_to_map

#: A 4 m x 3 m room turned 10 degrees off the grid, so that its traced walls run in steps.
ROOM = shapely.affinity.rotate(box(-2.0, -1.5, 2.0, 1.5), 10.0, origin=(0, 0))


Scan = tuple[np.ndarray, np.ndarray, np.ndarray, float]


def _scans(noise: float) -> list[Scan]:
    rng = np.random.default_rng(3)
    world = Map.from_shapely(ROOM)
    angles = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    scans = []
    for x, y, theta in [(-1.0, -0.5, 0.3), (0.0, 0.0, 1.2), (1.0, 0.6, -2.0), (0.5, -0.7, 2.5)]:
        pose = np.array([x, y, theta])
        ranges = cast_rays(world, pose, angles, 10.0)[0]
        scans.append((pose, ranges + rng.normal(0.0, noise, ranges.shape), angles, 10.0))
    return scans


def _hits(scans: list[Scan]) -> tuple[np.ndarray, np.ndarray]:
    hits, sensors = [], []
    for pose, ranges, angles, _ in scans:
        heading = pose[2] + angles
        ends = pose[:2] + ranges[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        hits.append(ends)
        sensors.append(np.broadcast_to(pose[:2], ends.shape))
    return np.vstack(hits), np.vstack(sensors)


def _wall_errors(geometry: Polygon) -> np.ndarray:
    """Distance to the true walls of the room's walls (a point every centimetre), away from
    the corners."""
    corners = shapely.points(np.asarray(ROOM.exterior.coords)[:-1])
    ring = np.asarray(shapely.segmentize(geometry.exterior, 0.01).coords)[:-1]
    points = shapely.points(ring)
    away = np.min([shapely.distance(points, c) for c in corners], axis=0) > 0.15
    return np.asarray(shapely.distance(points[away], ROOM.exterior))


def test_walls_traced_from_scans_move_onto_the_true_walls() -> None:
    scans = _scans(noise=0.003)
    grid = build_grid(scans, resolution=0.05)
    built = grid_to_map(grid, map_id="room", surface_offset=0.02, simplify=0.0)
    traced = geometry_from_geojson(built.map["geometry"])
    assert isinstance(traced, Polygon)
    hits, sensors = _hits(scans)
    fitted = fit_walls(traced, hits, sensors, WallFit())
    assert isinstance(fitted, Polygon)
    before, after = _wall_errors(traced), _wall_errors(fitted)
    # The trace runs in steps up to a cell off; the fitted walls lie on the true ones.
    assert before.max() > 0.02
    assert np.median(after) < 0.003
    assert after.max() < 0.008
    # Four straight walls: the steps are gone, and simplification leaves the four corners.
    assert len(fitted.exterior.coords) - 1 == 4
    assert abs(fitted.area - ROOM.area) < 0.01 * ROOM.area


def test_hits_seen_from_the_wall_side_do_not_move_it() -> None:
    square = box(0.0, 0.0, 1.0, 1.0)
    xs = np.linspace(0.2, 0.8, 31)
    hits = np.column_stack([xs, np.full_like(xs, 1.02)])
    inside = np.broadcast_to([0.5, 0.5], hits.shape)
    outside = np.broadcast_to([0.5, 2.0], hits.shape)
    fit = WallFit(simplify=0.0)
    seen_from_outside = fit_walls(square, hits, outside, fit)
    assert seen_from_outside.equals(square)
    moved = fit_walls(square, hits, inside, fit)
    top = np.asarray(moved.exterior.coords)[:-1]
    assert moved.area > 1.0
    assert np.abs(top[top[:, 1] > 0.5, 1] - 1.02).max() < 0.003


def test_no_vertex_moves_further_than_max_move() -> None:
    square = box(0.0, 0.0, 1.0, 1.0)
    xs = np.linspace(0.0, 1.0, 51)
    hits = np.column_stack([xs, np.full_like(xs, 1.09)])
    sensors = np.broadcast_to([0.5, 0.5], hits.shape)
    moved = fit_walls(square, hits, sensors, WallFit(reach=0.12, max_move=0.05, simplify=0.0))
    ring = np.asarray(moved.exterior.coords)[:-1]
    original = np.asarray(square.exterior.coords)[:-1]
    shift = shapely.distance(shapely.points(ring)[:, None], shapely.points(original)[None, :])
    assert np.asarray(shift).min(axis=1).max() <= 0.05 + 1e-9
    assert ring[:, 1].max() > 1.04
