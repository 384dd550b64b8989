"""Douglas-Peucker with topology preserved, ring by ring where rings are apart.

GEOS's topology-preserving simplifier (``shapely.simplify(..., preserve_topology=True)``) takes
every ring of a geometry in turn and rejects a flattening of a chain of vertices that would cross
a segment of any ring, as given or as already simplified, or pass over another ring. On a map
traced from a grid, whose obstacles are thousands of holes in one polygon, that costs time
growing with the square of the holes: 14 s for 14,500 holes, 104 s for 40,000, where each ring
alone takes a fraction of a millisecond.

A flattening stays within the tolerance of the chain it replaces: each vertex of the chain is
within it of the segment, and so, by convexity, is every point between them; the chain runs from
one end of the segment to the other, so every point of the segment has a point of the chain
within the tolerance. A ring simplified so stays within the tolerance of itself. Two rings
further apart than twice the tolerance can therefore never meet in any check of the simplifier:
:func:`simplify_rings` groups the rings that come that close (transitively), simplifies each
group on its own, with its rings in their order in the geometry, and puts the rings back where
they were. The result is what the simplifier gives on the whole geometry, vertex for vertex
(``tests/rlutf/test_simplify.py`` compares the two on traced maps, including rings a cell
apart).
"""

from __future__ import annotations

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Polygon

from rlutf._unionfind import group_roots

IntArray = NDArray[np.int64]

#: Rings closer than this many tolerances are simplified together (twice would do; the margin
#: covers rounding in the distance).
_APART = 2.5
#: Geometries with fewer rings are simplified whole (a few tens of milliseconds at this size).
_FEW_RINGS = 1000
#: Walls per piece of a ring in the search for rings near each other.
_PIECE = 32


def simplify_rings(geom: Polygon | MultiPolygon, tolerance: float) -> Polygon | MultiPolygon:
    """``shapely.simplify(geom, tolerance, preserve_topology=True)``, the same vertices, with
    each group of rings within :data:`_APART` tolerances of each other simplified apart.

    The result may be invalid where the simplifier's would be (callers repair it as before).
    """
    parts: list[Polygon] = list(shapely.get_parts(geom))
    rings = [r for p in parts for r in (p.exterior, *p.interiors)]
    done = None
    if len(rings) >= _FEW_RINGS and tolerance > 0:
        done = _by_groups(rings, _groups(rings, _APART * tolerance), tolerance)
    if done is None:
        return shapely.simplify(geom, tolerance, preserve_topology=True)
    out: list[Polygon] = []
    k = 0
    for p in parts:
        n = 1 + len(p.interiors)
        holes = [shapely.get_exterior_ring(h) for h in done[k + 1 : k + n]]
        out.append(Polygon(shapely.get_exterior_ring(done[k]), holes))
        k += n
    return out[0] if isinstance(geom, Polygon) else MultiPolygon(out)


def _by_groups(
    rings: list[shapely.LinearRing], group: IntArray, tolerance: float
) -> NDArray[np.object_] | None:
    """Each ring simplified with the others of its group (as a shell: the simplifier treats
    shells and holes alike), in the order of ``rings``; ``None`` where the whole geometry is
    simplified instead: one group holds most rings (nothing to gain), or a ring was lost."""
    sizes = np.bincount(group)
    if sizes.max() * 2 > len(rings):
        return None
    shells = shapely.polygons(rings)
    done = np.empty(len(rings), dtype=object)
    alone = np.flatnonzero(sizes[group] == 1)
    done[alone] = shapely.simplify(shells[alone], tolerance, preserve_topology=True)
    order = np.argsort(group, kind="stable")  # each group's rings in their order in geom
    for members in np.split(order, np.flatnonzero(np.diff(group[order])) + 1):
        if len(members) > 1:
            together = shapely.simplify(
                shapely.multipolygons(shells[members]), tolerance, preserve_topology=True
            )
            simplified = shapely.get_parts(together)
            if len(simplified) != len(members):
                return None
            done[members] = simplified
    return None if shapely.is_empty(done).any() else done


def _groups(rings: list[shapely.LinearRing], reach: float) -> IntArray:
    """A group number per ring: rings within ``reach`` of each other, transitively, share one
    (the smallest index among them).

    The rings are cut into pieces of at most :data:`_PIECE` walls for the search, so that the
    outer ring, which comes near every obstacle by the walls, costs a distance per nearby piece
    rather than per obstacle over all of its walls.
    """
    coords, which = shapely.get_coordinates(rings, return_index=True)
    starts = np.flatnonzero(np.r_[True, which[1:] != which[:-1]])
    ends = np.r_[starts[1:], len(which)] - 1  # each ring's last vertex (its first again)
    index: list[IntArray] = []
    piece_ring: list[int] = []
    for r, (s0, e0) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
        for lo in range(s0, e0, _PIECE):
            index.append(np.arange(lo, min(lo + _PIECE, e0) + 1))
            piece_ring.append(r)
    lengths = np.array([len(ix) for ix in index])
    pieces = shapely.linestrings(
        coords[np.concatenate(index)], indices=np.repeat(np.arange(len(index)), lengths)
    )
    tree = shapely.STRtree(pieces)
    i, j = tree.query(pieces, predicate="dwithin", distance=reach)
    ring = np.array(piece_ring, dtype=np.int64)
    ri, rj = ring[i], ring[j]
    other = ri < rj
    pairs = np.unique(np.stack([ri[other], rj[other]], axis=1), axis=0)
    return np.array(group_roots(len(rings), pairs.tolist()), dtype=np.int64)
