"""Topology-preserving simplification ring by ring: the same vertices as GEOS on the whole."""

import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPolygon, Polygon, box

from rlutf import map as map_module
from rlutf import simplify
from rlutf.map import Map, coarse_map
from rlutf.simplify import simplify_rings

CELL = 0.05


def _cluttered(seed: int, size: int = 160, blobs: int = 260) -> Polygon | MultiPolygon:
    """A room of ``size`` x ``size`` cells with obstacles of 1 to 4 cells a side dropped at
    random (some a cell apart, some against the wall, some touching at a corner), traced along
    the cell edges as a grid map is."""
    rng = np.random.default_rng(seed)
    corner = rng.integers(1, size - 5, size=(blobs, 2))
    sides = rng.integers(1, 5, size=(blobs, 2))
    obstacles = shapely.union_all(
        shapely.box(
            corner[:, 0], corner[:, 1], corner[:, 0] + sides[:, 0], corner[:, 1] + sides[:, 1]
        )
    )
    free = box(0, 0, size, size).difference(obstacles)
    return shapely.affinity.scale(free, CELL, CELL, origin=(0, 0))


def _same(a: shapely.Geometry, b: shapely.Geometry) -> bool:
    return (
        a.geom_type == b.geom_type
        and np.array_equal(shapely.get_coordinates(a), shapely.get_coordinates(b))
        and bool(shapely.equals_exact(a, b, 0.0))
    )


@pytest.fixture
def few_rings(monkeypatch: pytest.MonkeyPatch) -> None:
    """Take the ring-by-ring path on maps of a test's size (it starts at 1,000 rings)."""
    monkeypatch.setattr(simplify, "_FEW_RINGS", 2)


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("tolerance", [0.025, 0.05, 0.07, 0.1])
def test_same_vertices_as_the_whole_geometry_simplified(
    few_rings: None, seed: int, tolerance: float
) -> None:
    geom = _cluttered(seed)
    assert _same(
        simplify_rings(geom, tolerance), shapely.simplify(geom, tolerance, preserve_topology=True)
    )


def test_rings_near_each_other_are_simplified_together(few_rings: None) -> None:
    geom = _cluttered(1)
    rings = [r for p in shapely.get_parts(geom) for r in (p.exterior, *p.interiors)]
    groups = simplify._groups(rings, simplify._APART * 0.07)
    sizes = np.bincount(groups)[groups]
    # The case the groups are for is in this map: rings apart and rings that meet in the
    # simplifier's checks (one a cell from another, or from the wall).
    assert (sizes == 1).any() and (sizes > 1).any()
    # Every pair of rings within reach is in one group.
    tree = shapely.STRtree(rings)
    a, b = tree.query(rings, predicate="dwithin", distance=simplify._APART * 0.07)
    assert np.array_equal(groups[a], groups[b])


def test_a_multipolygon_keeps_its_parts_in_order(few_rings: None) -> None:
    left, right = _cluttered(4, size=80, blobs=60), _cluttered(5, size=80, blobs=60)
    geom = MultiPolygon(
        [*shapely.get_parts(left), *shapely.get_parts(shapely.affinity.translate(right, 5.0))]
    )
    assert _same(simplify_rings(geom, 0.05), shapely.simplify(geom, 0.05, preserve_topology=True))


def test_one_group_holding_most_rings_is_simplified_whole(few_rings: None) -> None:
    # Obstacles a cell apart everywhere: every ring within reach of the next.
    cells = [box(x, y, x + 1, y + 1) for x in range(1, 40, 2) for y in range(1, 40, 2)]
    geom = shapely.affinity.scale(
        box(0, 0, 41, 41).difference(shapely.union_all(cells)), CELL, CELL, origin=(0, 0)
    )
    assert _same(simplify_rings(geom, 0.07), shapely.simplify(geom, 0.07, preserve_topology=True))


def test_the_coarse_map_is_the_same_map(monkeypatch: pytest.MonkeyPatch) -> None:
    # Above the ring count where the groups start, as a traced warehouse or a cluttered site
    # is: the walls a localizer tracks on are those it tracked on when the whole map was
    # simplified at once.
    geom = _cluttered(6, size=400, blobs=1600)
    assert len(shapely.get_parts(geom)[0].interiors) >= simplify._FEW_RINGS
    monkeypatch.setattr(map_module, "COARSE_KEEP", 1.0)  # boxes lose few walls: keep them
    world = Map.from_shapely(geom)
    coarse = coarse_map(world, 0.07)
    assert coarse is not world
    monkeypatch.setattr(
        map_module,
        "simplify_rings",
        lambda g, t: shapely.simplify(g, t, preserve_topology=True),
    )
    whole = coarse_map(Map.from_shapely(geom), 0.07)
    assert np.array_equal(coarse.segments, whole.segments)
