"""Occupancy grid to free-space polygons: components, specks, contour tracing, simplification.

Free space is the set of free cells; occupied and unknown cells are walls. Free cells are
connected through their sides (4-connectivity), so two rooms that touch only at a cell corner
are separate components, which is also how the tracer below separates them; obstacles are
connected through sides and corners (8-connectivity).

Tracing runs :func:`skimage.measure.find_contours` at level 0.5 on the free mask padded with
walls. Its contours pass through the midpoints of cell edges and cut every corner by half a
cell, which would lose about half a cell of area along each wall and let rays slip past the
corners of obstacles; the cut corners are put back (:func:`_square_corners`), so the rings run
exactly along the cell edges and the polygons are the union of the free cells (area equal to
the free cell count to rounding; rays equal to a grid ray march). The rings are nested by
containment (even depth: outer boundaries; odd: obstacles), then simplified with
Douglas-Peucker (topology preserving) at half a cell by default, which turns staircases into
straight walls without moving any wall by more than the tolerance.

Selection and specks: by default only the largest free component is kept; ``component`` may
name another one by its index in the listing (largest first) or by a map-frame point inside it,
or ``"all"`` keeps every component of at least ``min_area``. Obstacles (holes) with an area
below ``min_hole_area`` are filled in as free space: single-cell specks are sensor noise or
people in a SLAM map, and a localizer gains nothing from walls that small.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import shapely
import shapely.affinity
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Polygon
from skimage import measure

from rlutf.simplify import simplify_rings
from service.maps.mapimport.errors import ComponentError, EmptyMapError, MapImportError
from service.maps.mapimport.grid import BoolArray, FloatArray, OccupancyGrid

# scikit-image ships partial annotations; these typed aliases keep mypy strict satisfied.
_label: Callable[..., NDArray[np.int64]] = measure.label
_find_contours: Callable[..., list[FloatArray]] = measure.find_contours

#: Free components smaller than this (square metres) are dropped when keeping ``"all"``.
DEFAULT_MIN_AREA = 1.0
#: Obstacles smaller than this (square metres) are filled in: single cells at 5 cm. Larger
#: thresholds remove more SLAM noise but also real thin posts: on Nav2's depot map, 0.01 m2
#: (up to 3 cells) fills 56 obstacles and makes 1.5 % of beams miss what the grid would hit.
DEFAULT_MIN_HOLE_AREA = 0.005
#: Default Douglas-Peucker tolerance, as a fraction of the resolution. Measured on Nav2's
#: depot and tb3_sandbox maps: at 0.5 cell the area stays within 0.01 % of the free cells and
#: 99.8 % of beams are within two cells of a grid ray march, with 10 to 30 % fewer walls than
#: at 0.25 cell (which is still exact); at 1 cell only about 97 % of beams agree.
DEFAULT_SIMPLIFY_CELLS = 0.5

#: How far (cells) rings stop short of a corner where free cells touch only diagonally.
_PINCH = 1e-3

ComponentSpec = int | tuple[float, float] | Literal["all"] | None


@dataclass(frozen=True)
class Component:
    """A 4-connected component of free cells.

    Attributes:
        index: position in the listing, largest first.
        cells: number of free cells.
        area: ``cells * resolution**2``, square metres.
        point: a map-frame point inside it (the centre of its cell nearest to its centroid).
        kept: whether it is part of the result.
        reason: why it was kept or dropped.
    """

    index: int
    cells: int
    area: float
    point: tuple[float, float]
    kept: bool
    reason: str


@dataclass(frozen=True, eq=False)
class Polygonized:
    """Result of :func:`polygonize`.

    Attributes:
        geometry: free space in the map frame, valid.
        free: ``(rows, cols)`` the free mask that was traced (kept components, specks filled).
        components: every free component of the grid, largest first.
        holes_kept: obstacles kept as holes.
        holes_filled: obstacles filled in as specks.
        filled_area: their total area, square metres.
        tolerance: the simplification tolerance used, metres.
    """

    geometry: Polygon | MultiPolygon
    free: BoolArray
    components: tuple[Component, ...]
    holes_kept: int
    holes_filled: int
    filled_area: float
    tolerance: float

    @property
    def wall_count(self) -> int:
        """Number of wall segments (edges of all rings)."""
        polys = [self.geometry] if isinstance(self.geometry, Polygon) else self.geometry.geoms
        return sum(len(r.coords) - 1 for p in polys for r in (p.exterior, *p.interiors))

    def report(self, grid: OccupancyGrid) -> list[str]:
        """Human-readable lines: what was kept and dropped, and how the area compares."""
        cell = grid.cell_area
        occupied = int(np.count_nonzero(grid.occupied))
        unknown = grid.data.size - grid.free_cells - occupied
        rows, cols = grid.shape
        x0, y0, yaw = grid.origin
        lines = [
            f"grid: {cols} x {rows} cells of {grid.resolution:g} m, "
            f"origin ({x0:g}, {y0:g}, yaw {yaw:g})",
            f"cells: {grid.free_cells} free ({grid.free_cells * cell:.2f} m2), {occupied} "
            f"occupied, {unknown} unknown (unknown counts as wall)",
            f"free components (4-connected, largest first): {len(self.components)}",
        ]
        shown = [c for c in self.components if c.kept or c.index < 10]
        lines.extend(
            f"  [{c.index}] {c.cells} cells, {c.area:.2f} m2, point "
            f"({c.point[0]:.2f}, {c.point[1]:.2f}): {'kept' if c.kept else 'dropped'}"
            f" ({c.reason})"
            for c in shown
        )
        rest = [c for c in self.components if c not in shown]
        if rest:
            lines.append(
                f"  ... {len(rest)} more dropped, {sum(c.area for c in rest):.2f} m2 in all"
            )
        lines.append(
            f"obstacles inside: {self.holes_kept} kept, {self.holes_filled} specks filled "
            f"({self.filled_area:.3f} m2)"
        )
        traced = float(np.count_nonzero(self.free)) * cell
        area = float(self.geometry.area)
        lines.append(
            f"polygons: area {area:.2f} m2 vs {traced:.2f} m2 of kept cells "
            f"({100.0 * (area - traced) / traced:+.2f} %), {self.wall_count} walls, "
            f"simplify tolerance {self.tolerance:g} m"
        )
        return lines


#: Grid rows a component's centroid and nearest cell are computed over at once: the
#: temporaries of a large map are a band's (regionprops took 1.2 GB for a map of 24 million
#: cells, the coordinates of its largest component and their distances to its centroid).
_BAND_ROWS = 256


def _points(labels: NDArray[np.int64], counts: NDArray[np.int64]) -> NDArray[np.int64]:
    """Per component 1..n (``counts``: their cells), ``(row, col)`` of its cell nearest its
    centroid (the first in row order of those as near); row 0 is unused."""
    n = len(counts)
    rows, cols = labels.shape
    bands = [slice(r, min(rows, r + _BAND_ROWS)) for r in range(0, rows, _BAND_ROWS)]
    sum_r, sum_c = np.zeros(n + 1), np.zeros(n + 1)
    for band in bands:
        lab = labels[band].ravel()
        shape = (band.stop - band.start, cols)
        row_of = np.broadcast_to(np.arange(band.start, band.stop, dtype=np.float64)[:, None], shape)
        col_of = np.broadcast_to(np.arange(cols, dtype=np.float64), shape)
        sum_r += np.bincount(lab, row_of.ravel(), minlength=n + 1)
        sum_c += np.bincount(lab, col_of.ravel(), minlength=n + 1)
    size = np.concatenate([[1.0], counts])
    centre_r, centre_c = sum_r / size, sum_c / size
    best = np.full(n + 1, np.inf)
    where = np.zeros((n + 1, 2), dtype=np.int64)
    for band in bands:
        r, c = np.nonzero(labels[band])
        lab = labels[band][r, c]
        r = r + band.start
        d = (r - centre_r[lab]) ** 2 + (c - centre_c[lab]) ** 2
        order = np.lexsort((d, lab))  # by component, then distance, then row order
        first = order[np.flatnonzero(np.diff(lab[order], prepend=-1))]
        better = d[first] < best[lab[first]]
        k = lab[first][better]
        best[k] = d[first][better]
        where[k, 0], where[k, 1] = r[first][better], c[first][better]
    return where


def _select(
    grid: OccupancyGrid, labels: NDArray[np.int64], spec: ComponentSpec, min_area: float
) -> tuple[Component, ...]:
    """List the components (labels renumbered largest first) and mark which are kept."""
    counts = np.bincount(labels.ravel())[1:]
    order = np.argsort(-counts, kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    cells = _points(labels, counts)[1:][order]  # largest first
    points = [(float(xy[0]), float(xy[1])) for xy in grid.cell_centres(cells[:, 0], cells[:, 1])]
    chosen: set[int]
    if spec is None:
        chosen, why = {0}, "largest"
    elif spec == "all":
        chosen = {i for i in range(len(order)) if counts[order[i]] * grid.cell_area >= min_area}
        why = f"at least {min_area:g} m2"
        if not chosen:
            raise EmptyMapError(f"no free component has an area of at least {min_area:g} m2")
    elif isinstance(spec, tuple):
        cell = np.floor(grid.to_local([spec]) / grid.resolution)[0]
        col, row = int(cell[0]), int(cell[1])
        rows, cols = grid.shape
        where = f"point ({spec[0]:g}, {spec[1]:g})"
        if not (0 <= row < rows and 0 <= col < cols):
            # its corners, in the map frame (a grid's origin may be turned)
            ends = grid.to_world(
                np.array([[0.0, 0.0], [cols, 0.0], [0.0, rows], [cols, rows]]) * grid.resolution
            )
            (x0, y0), (x1, y1) = ends.min(axis=0), ends.max(axis=0)
            raise ComponentError(
                f"component: {where} is outside the grid, which spans x {x0:g} to {x1:g} m and "
                f"y {y0:g} to {y1:g} m in the map frame"
            )
        if labels[row, col] == 0:
            state = "occupied" if grid.occupied[row, col] else "unknown"
            raise ComponentError(f"component: {where} is in an {state} cell, not free space")
        chosen, why = {int(rank[labels[row, col] - 1])}, f"contains {where}"
    else:
        if not 0 <= spec < len(order):
            raise ComponentError(
                f"component: index {spec} does not exist; the grid has {len(order)} free "
                f"component(s), numbered 0 to {len(order) - 1} largest first"
            )
        chosen, why = {spec}, "selected by index"
    other = "below min_area" if spec == "all" else "not selected"
    return tuple(
        Component(
            i,
            int(counts[order[i]]),
            float(counts[order[i]]) * grid.cell_area,
            points[i],
            i in chosen,
            why if i in chosen else other,
        )
        for i in range(len(order))
    )


def fill_small_holes(free: BoolArray, max_cells: float) -> tuple[BoolArray, int, int, int]:
    """Fill obstacles (8-connected non-free regions not touching the border) below a size.

    Args:
        free: ``(rows, cols)`` free mask.
        max_cells: obstacles with fewer cells than this are filled (a count within 1e-9 of
            it counts as equal, so that square-metre thresholds survive rounding).

    Returns:
        ``(filled mask, holes kept, holes filled, cells filled)``.
    """
    padded = np.pad(~free, 1, constant_values=True)
    labels = _label(padded, connectivity=2)
    counts = np.bincount(labels.ravel())
    counts[0] = 0
    counts[labels[0, 0]] = 0  # the outside, connected to the padding
    holes = np.flatnonzero(counts)
    small = holes[counts[holes] < max_cells * (1.0 - 1e-9)]
    lookup = np.zeros(len(counts), dtype=bool)  # a look-up table, not np.isin's sort
    lookup[small] = True
    fill = lookup[labels[1:-1, 1:-1]]
    return free | fill, len(holes) - len(small), len(small), int(counts[small].sum())


def _square_corners(contour: FloatArray, padded: NDArray[np.uint8]) -> FloatArray:
    """Put back the cell corners that marching squares cuts, making the ring rectilinear.

    Contour vertices lie on cell edges: one coordinate is a cell centre (integer), the other
    halfway between two centres (integer + 0.5). A segment that changes both coordinates cuts
    a corner; the cut corner is the point whose coordinates are both half-integers. Where two
    free cells meet only at that corner (a saddle), each ring stops ``_PINCH`` short of it so
    that the rings do not touch, which keeps the polygons valid without a costly repair.
    """
    p, q = contour[:-1], contour[1:]
    diagonal = (p[:, 0] != q[:, 0]) & (p[:, 1] != q[:, 1])
    p_d, q_d = p[diagonal], q[diagonal]
    half_p = np.abs(p_d - np.floor(p_d) - 0.5) < 0.25
    corner = np.where(half_p, p_d, q_d)
    lo = np.floor(corner).astype(np.int64)
    v00, v11 = padded[lo[:, 0], lo[:, 1]], padded[lo[:, 0] + 1, lo[:, 1] + 1]
    v01, v10 = padded[lo[:, 0], lo[:, 1] + 1], padded[lo[:, 0] + 1, lo[:, 1]]
    saddle = (v00 == v11) & (v01 == v10) & (v00 != v01)
    towards_free = np.sign(0.5 * (p_d + q_d) - corner)
    corner[saddle] += _PINCH * towards_free[saddle]
    out = np.empty((len(p) + len(corner), 2))
    slot = np.arange(len(p)) + np.concatenate([[0], np.cumsum(diagonal)[:-1]])
    out[slot] = p
    out[slot[diagonal] + 1] = corner
    # Start the ring at a corner: Douglas-Peucker keeps the start, and a start on an edge
    # half a cell from a corner would let it cut that corner.
    first = int(slot[diagonal][0]) + 1 if len(corner) else 0
    return np.vstack([out[first:], out[:first], out[first : first + 1]])


def trace_free_space(free: BoolArray, resolution: float) -> Polygon | MultiPolygon:
    """The union of the free cells as polygons in the grid frame (metres); unsimplified.

    Rings run exactly along cell edges, except where free cells touch only at a corner: there
    the free space is pinched off ``_PINCH`` cells short of the corner on both sides.

    Raises:
        EmptyMapError: no free cell.
    """
    if not free.any():
        raise EmptyMapError("the grid has no free space to trace")
    # 0 and 1 in a byte a cell (find_contours makes its own float64 copy: not a second one)
    padded = np.pad(free, 1).astype(np.uint8)
    contours = _find_contours(padded, 0.5, fully_connected="low")
    # Contour (row, col) in the padded array -> corners squared -> grid-frame metres.
    rings: list[FloatArray] = [
        (_square_corners(c, padded)[:, ::-1] - 0.5) * resolution for c in contours if len(c) >= 4
    ]
    polys = [Polygon(r) for r in rings]
    tree = shapely.STRtree(polys)
    # A ring's first vertex is the midpoint of a cell edge, never a point where rings touch.
    inside, outer = tree.query(shapely.points([r[0] for r in rings]), predicate="within")
    depth = np.bincount(inside, minlength=len(rings))
    holes: dict[int, list[FloatArray]] = {}
    for i, j in zip(inside.tolist(), outer.tolist(), strict=True):
        if depth[i] % 2 == 1 and depth[j] == depth[i] - 1:
            holes.setdefault(j, []).append(rings[i])
    shells = [Polygon(rings[j], holes.get(int(j), [])) for j in np.flatnonzero(depth % 2 == 0)]
    return polygonal(shells[0] if len(shells) == 1 else MultiPolygon(shells))


def polygonal(geom: shapely.Geometry) -> Polygon | MultiPolygon:
    """Make a geometry valid and keep its polygonal parts."""
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    parts = [g for g in shapely.get_parts(geom) if isinstance(g, Polygon) and not g.is_empty]
    if not parts:
        raise EmptyMapError("the simplified free space is empty")
    return parts[0] if len(parts) == 1 else MultiPolygon(parts)


def polygonize(
    grid: OccupancyGrid,
    *,
    component: ComponentSpec = None,
    min_area: float = DEFAULT_MIN_AREA,
    min_hole_area: float = DEFAULT_MIN_HOLE_AREA,
    simplify: float | None = None,
) -> Polygonized:
    """Free space of a grid as valid polygons in the map frame.

    Args:
        grid: the occupancy grid.
        component: which free component to keep: None for the largest, an index into the
            listing (largest first), a map-frame point ``(x, y)`` inside it, or ``"all"``.
        min_area: with ``"all"``, components smaller than this (square metres) are dropped.
        min_hole_area: obstacles smaller than this (square metres) are filled in.
        simplify: Douglas-Peucker tolerance in metres; None for half a cell, 0 for none. It
            may not exceed the resolution.

    Returns:
        The geometry with what was kept and dropped.

    Raises:
        EmptyMapError: the grid has no free cell.
        ComponentError: ``component`` names no component.
        MapImportError: ``simplify`` is negative or above the resolution.
    """
    tolerance = DEFAULT_SIMPLIFY_CELLS * grid.resolution if simplify is None else simplify
    if not (math.isfinite(tolerance) and 0.0 <= tolerance <= grid.resolution):
        raise MapImportError(
            f"simplify: tolerance must be between 0 and the resolution "
            f"{grid.resolution:g} m, got {tolerance:g}"
        )
    if not grid.free.any():
        raise EmptyMapError("the map has no free space: every cell is occupied or unknown")
    labels = np.asarray(_label(grid.free, connectivity=1), dtype=np.int64)
    components = _select(grid, labels, component, min_area)
    order = np.argsort(-np.bincount(labels.ravel())[1:], kind="stable")
    kept_labels = [int(order[c.index]) + 1 for c in components if c.kept]
    kept = np.zeros(len(order) + 1, dtype=bool)  # a look-up table, not np.isin's copies
    kept[kept_labels] = True
    free = kept[labels]
    del labels  # a map of 24 million cells: 192 MB, before the next labelling
    free, holes_kept, holes_filled, cells_filled = fill_small_holes(
        free, min_hole_area / grid.cell_area
    )
    local = trace_free_space(free, grid.resolution)
    if tolerance > 0:
        local = polygonal(simplify_rings(local, tolerance))
    geom = polygonal(shapely.affinity.affine_transform(local, list(grid.affine)))
    geom = polygonal(shapely.orient_polygons(geom))
    return Polygonized(
        geometry=geom,
        free=free,
        components=components,
        holes_kept=holes_kept,
        holes_filled=holes_filled,
        filled_area=cells_filled * grid.cell_area,
        tolerance=tolerance,
    )
