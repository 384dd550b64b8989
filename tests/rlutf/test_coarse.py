"""Tracking on a traced map's simplified walls, answering on the map (``coarse_tolerance``)."""

import math

import numpy as np
import pytest
import shapely
from shapely import affinity
from shapely.geometry import MultiPolygon, Polygon, box

from rlutf.errors import ConfigError
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.map import Map, coarse_map
from rlutf.sim import LidarModel, make_building, simulate_scan

CELL = 0.05


def _room(degrees: float) -> Polygon | MultiPolygon:
    """A 6 m x 4 m room with a pillar, turned by ``degrees`` about its centre."""
    room = box(0, 0, 6, 4).difference(box(2.5, 1.5, 3.1, 2.1))
    return affinity.rotate(room, degrees, origin=(3, 2))


def _traced(geom: Polygon | MultiPolygon) -> Map:
    """``geom`` as a map built from a grid would trace it: the union of the 5 cm cells whose
    centre is free, simplified at half a cell (walls in steps where they are not on the grid's
    axes)."""
    x0, y0, x1, y1 = geom.bounds
    i = np.arange(math.floor(x0 / CELL), math.ceil(x1 / CELL))
    j = np.arange(math.floor(y0 / CELL), math.ceil(y1 / CELL))
    ii, jj = (a.ravel() for a in np.meshgrid(i, j))
    free = shapely.contains_xy(geom, (ii + 0.5) * CELL, (jj + 0.5) * CELL)
    cells = shapely.unary_union(
        [box(a, b, a + 1, b + 1) for a, b in zip(ii[free], jj[free], strict=True)]
    )
    union = affinity.scale(cells, CELL, CELL, origin=(0, 0))
    return Map.from_shapely(shapely.simplify(union, CELL / 2, preserve_topology=True))


def test_a_drawn_map_is_its_own_coarse_map() -> None:
    world = make_building(np.random.default_rng(0))
    assert coarse_map(world, 0.07) is world
    room = Map.from_shapely(_room(7.0))
    assert coarse_map(room, 0.07) is room


def test_a_traced_map_is_simplified_once() -> None:
    traced = _traced(_room(7.0))
    coarse = coarse_map(traced, 0.07)
    assert coarse is not traced
    # The steps are gone: about the 8 walls of the drawn room, against 100 or so traced.
    assert len(coarse.segments) <= 12
    assert len(traced.segments) > 50
    assert coarse_map(traced, 0.07) is coarse  # made once per map and tolerance
    assert coarse_map(traced, 0.0) is traced
    assert abs(coarse.geometry.area - traced.geometry.area) < 0.01 * traced.geometry.area


def test_the_localizer_tracks_on_the_coarse_map_only_where_it_helps() -> None:
    traced = _traced(_room(7.0))
    drawn = Map.from_shapely(_room(7.0))
    pose = np.array([1.0, 1.0, 0.0])
    assert Localizer(traced, pose).tracking_map is coarse_map(traced, 0.07)
    assert Localizer(drawn, pose).tracking_map is drawn
    assert Localizer(traced, pose, LocalizerConfig(coarse_tolerance=0.0)).tracking_map is traced
    assert Localizer(traced, pose, LocalizerConfig.paper()).tracking_map is traced
    assert Localizer(traced, pose, LocalizerConfig(refine=False)).tracking_map is traced


def test_the_map_tracked_on_follows_a_new_map() -> None:
    traced, other = _traced(_room(7.0)), _traced(_room(11.0))
    loc = Localizer(traced, np.array([1.0, 1.0, 0.0]))
    assert loc.tracking_map is coarse_map(traced, 0.07)
    loc.set_map(other)
    assert loc.tracking_map is coarse_map(other, 0.07)
    loc.set_map(traced)
    assert loc.tracking_map is coarse_map(traced, 0.07)


def test_negative_coarse_tolerance_is_refused() -> None:
    with pytest.raises(ConfigError, match="coarse_tolerance"):
        LocalizerConfig(coarse_tolerance=-0.01)


def _errors(config: LocalizerConfig, degrees: float, starts: int) -> np.ndarray:
    """Position errors (cm) of one update each from a prediction 6 cm and 2 degrees off, on the
    traced map of a room whose scans come from the drawn room."""
    geom = _room(degrees)
    drawn, traced = Map.from_shapely(geom), _traced(geom)
    rng = np.random.default_rng(0)
    lidar = LidarModel(beams=360, noise=0.02)
    out = []
    for i in range(starts):
        x = rng.uniform(1, 5)
        y = rng.uniform(0.8, 1.2) if i % 2 else rng.uniform(2.6, 3.3)
        heading = rng.uniform(-3, 3)
        x, y = affinity.rotate(shapely.Point(x, y), degrees, origin=(3, 2)).coords[0]
        truth = np.array([x, y, heading])
        scan = simulate_scan(drawn, truth, lidar, rng)
        turn = rng.uniform(0, 2 * math.pi)
        start = truth + np.array([0.06 * math.cos(turn), 0.06 * math.sin(turn), math.radians(2)])
        loc = Localizer(traced, start, config, seed=i, spread=(0.0, 0.0))
        pose = loc.update(np.zeros(3), scan).pose
        out.append(100.0 * math.hypot(*(pose[:2] - truth[:2])))
    return np.array(out)


def test_tracking_on_the_simplified_walls_escapes_the_steps_of_a_traced_wall() -> None:
    # Walls 7 degrees off the grid's axes are traced as steps a cell high. Refined on them
    # from a prediction a few centimetres off, some updates stop on a step, over a centimetre
    # from the truth; on the simplified walls the refinement reaches the basin of the map's own
    # bottom, and the answer (refined on the map) stays within the noise's reach.
    plain = _errors(LocalizerConfig(coarse_tolerance=0.0), 7.0, 30)
    coarse = _errors(LocalizerConfig(), 7.0, 30)
    assert plain.max() > 1.0
    assert coarse.max() < 0.75
    assert np.sqrt(np.mean(coarse**2)) < 0.8 * np.sqrt(np.mean(plain**2))
