"""Polygon maps: free space as polygons, walls as segments, and a grid index over the walls.

The free space is the interior of the map's polygons; their boundaries (outer rings and holes)
are the walls a laser sees. Maps come from a GeoJSON ``Polygon`` or ``MultiPolygon`` (see the
wire contract) or a shapely geometry and are validated with errors that say what is wrong and
where.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar, cast

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient
from shapely.validation import explain_validity

from rlutf.errors import MapError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: ``(segments, x0, y0, cell, nx, ny, cell_start, cell_walls)``: see :attr:`Map.grid`.
Grid = tuple[FloatArray, float, float, float, int, int, IntArray, IntArray]
T = TypeVar("T")

#: Default side of a cell of the wall index, metres.
DEFAULT_CELL_SIZE = 1.0
#: Most cell windows whose wall lists the index remembers (each a small int array).
_MEMO_LIMIT = 4096


def _ring_array(ring: Any, where: str) -> FloatArray:
    try:
        arr = np.asarray(ring, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MapError(f"{where}: positions must be [x, y] number pairs") from err
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise MapError(f"{where}: positions must be [x, y] pairs, got shape {arr.shape}")
    arr = arr[:, :2]
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MapError(f"{where}[{i}]: non-finite coordinate {arr[i].tolist()}")
    if len(arr) < 4:
        raise MapError(f"{where}: a ring needs at least 4 positions, got {len(arr)}")
    if not np.array_equal(arr[0], arr[-1]):
        raise MapError(
            f"{where}: ring is not closed (first {arr[0].tolist()} != last {arr[-1].tolist()})"
        )
    return arr


def _polygon_from_rings(rings: Any, where: str) -> Polygon:
    if not isinstance(rings, Sequence) or isinstance(rings, str) or len(rings) == 0:
        raise MapError(f"{where}: a Polygon needs at least one ring")
    shell = _ring_array(rings[0], f"{where}[0]")
    holes = [_ring_array(r, f"{where}[{i}]") for i, r in enumerate(rings[1:], start=1)]
    return Polygon(shell, holes)


def geometry_from_geojson(geometry: Mapping[str, Any]) -> Polygon | MultiPolygon:
    """Build a shapely geometry from a GeoJSON ``Polygon`` or ``MultiPolygon`` mapping.

    Args:
        geometry: ``{"type": ..., "coordinates": ...}`` in metres.

    Returns:
        The shapely geometry (not yet validated for self-intersection; see :class:`Map`).

    Raises:
        MapError: wrong type, unclosed ring, too few positions, non-finite coordinate.
    """
    kind = geometry.get("type")
    coords = geometry.get("coordinates")
    if kind == "Polygon":
        return _polygon_from_rings(coords, "coordinates")
    if kind == "MultiPolygon":
        if not isinstance(coords, Sequence) or len(coords) == 0:
            raise MapError("coordinates: a MultiPolygon needs at least one polygon")
        return MultiPolygon(
            [_polygon_from_rings(p, f"coordinates[{i}]") for i, p in enumerate(coords)]
        )
    raise MapError(f"type: expected 'Polygon' or 'MultiPolygon', got {kind!r}")


def geometry_to_geojson(geom: Polygon | MultiPolygon) -> dict[str, Any]:
    """GeoJSON mapping of a polygonal geometry (rings closed, coordinates as lists)."""

    def rings(p: Polygon) -> list[list[list[float]]]:
        out = [np.asarray(p.exterior.coords)[:, :2].tolist()]
        out.extend(np.asarray(r.coords)[:, :2].tolist() for r in p.interiors)
        return out

    if isinstance(geom, Polygon):
        return {"type": "Polygon", "coordinates": rings(geom)}
    return {"type": "MultiPolygon", "coordinates": [rings(p) for p in geom.geoms]}


@dataclass(frozen=True, eq=False)
class WallIndex:
    """A uniform grid over the map bounds listing, per cell, the walls that touch it.

    ``cell_start[c]:cell_start[c + 1]`` indexes ``cell_walls`` for cell ``c = row * nx + col``.
    """

    origin: tuple[float, float]
    cell_size: float
    nx: int
    ny: int
    cell_start: IntArray
    cell_walls: IntArray
    _memo: dict[tuple[int, int, int, int], IntArray] = field(
        default_factory=dict, repr=False, compare=False
    )

    def walls_near(self, x: float, y: float, radius: float) -> IntArray:
        """Indices of the walls in the cells that overlap the square of half-side ``radius``.

        A superset of the walls within ``radius`` of ``(x, y)``; sorted and unique.
        """
        c0 = max(math.floor((x - radius - self.origin[0]) / self.cell_size), 0)
        c1 = min(math.floor((x + radius - self.origin[0]) / self.cell_size), self.nx - 1)
        r0 = max(math.floor((y - radius - self.origin[1]) / self.cell_size), 0)
        r1 = min(math.floor((y + radius - self.origin[1]) / self.cell_size), self.ny - 1)
        if c0 > c1 or r0 > r1:
            return np.empty(0, dtype=np.int64)
        key = (c0, c1, r0, r1)
        hit = self._memo.get(key)
        if hit is not None:
            return hit
        parts = [
            self.cell_walls[
                self.cell_start[r * self.nx + c0] : self.cell_start[r * self.nx + c1 + 1]
            ]
            for r in range(r0, r1 + 1)
        ]
        found = np.unique(np.concatenate(parts))
        found.flags.writeable = False
        if len(self._memo) >= _MEMO_LIMIT:
            self._memo.clear()
        self._memo[key] = found
        return found


def _build_index(segments: FloatArray, cell_size: float) -> WallIndex:
    x0 = float(min(segments[:, 0].min(), segments[:, 2].min()))
    y0 = float(min(segments[:, 1].min(), segments[:, 3].min()))
    x1 = float(max(segments[:, 0].max(), segments[:, 2].max()))
    y1 = float(max(segments[:, 1].max(), segments[:, 3].max()))
    nx = max(math.ceil((x1 - x0) / cell_size), 1)
    ny = max(math.ceil((y1 - y0) / cell_size), 1)
    cells: list[list[int]] = [[] for _ in range(nx * ny)]
    for i, (ax, ay, bx, by) in enumerate(segments):
        # Conservative: every cell of the segment's bounding box that the segment's
        # supporting line passes near. Walls are short compared to a map, so the box is tight.
        ca = min(max(int((min(ax, bx) - x0) // cell_size), 0), nx - 1)
        cb = min(max(int((max(ax, bx) - x0) // cell_size), 0), nx - 1)
        ra = min(max(int((min(ay, by) - y0) // cell_size), 0), ny - 1)
        rb = min(max(int((max(ay, by) - y0) // cell_size), 0), ny - 1)
        dx, dy = bx - ax, by - ay
        length = math.hypot(dx, dy)
        half_diag = cell_size * math.sqrt(0.5)
        for r in range(ra, rb + 1):
            cy = y0 + (r + 0.5) * cell_size
            for c in range(ca, cb + 1):
                cx = x0 + (c + 0.5) * cell_size
                if length > 0 and abs(dx * (cy - ay) - dy * (cx - ax)) / length > half_diag:
                    continue
                cells[r * nx + c].append(i)
    counts = np.fromiter((len(c) for c in cells), dtype=np.int64, count=len(cells))
    start = np.zeros(len(cells) + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    flat = np.fromiter((i for c in cells for i in c), dtype=np.int64, count=int(start[-1]))
    return WallIndex((x0, y0), cell_size, nx, ny, start, flat)


@dataclass(frozen=True, eq=False)
class Map:
    """A validated polygon map.

    Attributes:
        geometry: free space, a shapely ``Polygon`` or ``MultiPolygon`` in metres.
        segments: ``(M, 4)`` walls as ``x1, y1, x2, y2`` rows, metres, each directed so that the
            free space is on its left (outer rings counter-clockwise, holes clockwise).
        index: grid index of the walls, for range-limited queries.
        wall_start: ``(M,)`` wall start points as complex numbers ``x + iy``.
        wall_direction: ``(M,)`` wall vectors (end minus start) as complex numbers.
        wall_length: ``(M,)`` wall lengths, metres.
    """

    geometry: Polygon | MultiPolygon
    segments: FloatArray = field(repr=False)
    index: WallIndex = field(repr=False)
    wall_start: NDArray[np.complex128] = field(repr=False, init=False)
    wall_direction: NDArray[np.complex128] = field(repr=False, init=False)
    wall_length: FloatArray = field(repr=False, init=False)
    _derived: dict[str, object] = field(repr=False, init=False, default_factory=dict)

    def __post_init__(self) -> None:
        # Walls as complex numbers (start, end - start), for the ray caster.
        s = self.segments
        object.__setattr__(self, "wall_start", s[:, 0] + 1j * s[:, 1])
        object.__setattr__(self, "wall_direction", (s[:, 2] - s[:, 0]) + 1j * (s[:, 3] - s[:, 1]))
        object.__setattr__(self, "wall_length", np.abs(self.wall_direction))

    @classmethod
    def from_shapely(
        cls, geom: Polygon | MultiPolygon, *, cell_size: float = DEFAULT_CELL_SIZE
    ) -> Map:
        """Validate a shapely geometry and build the map.

        Raises:
            MapError: not polygonal, empty, invalid (self-intersecting and the like), zero area.
        """
        if not isinstance(geom, Polygon | MultiPolygon):
            raise MapError(f"geometry: expected a Polygon or MultiPolygon, got {geom.geom_type}")
        if geom.is_empty:
            raise MapError("geometry: the map is empty")
        coords = shapely.get_coordinates(geom)
        if not np.isfinite(coords).all():
            raise MapError("geometry: non-finite coordinate")
        if not geom.is_valid:
            raise MapError(f"geometry: invalid polygon: {explain_validity(geom)}")
        if geom.area <= 0.0:
            raise MapError("geometry: the map has zero area")
        if not cell_size > 0:
            raise MapError(f"cell_size: must be positive, got {cell_size}")
        segments = _segments_of(geom)
        shapely.prepare(geom)
        return cls(geom, segments, _build_index(segments, cell_size))

    @classmethod
    def from_geojson(
        cls, geometry: Mapping[str, Any], *, cell_size: float = DEFAULT_CELL_SIZE
    ) -> Map:
        """Build and validate a map from a GeoJSON ``Polygon``/``MultiPolygon`` mapping."""
        return cls.from_shapely(geometry_from_geojson(geometry), cell_size=cell_size)

    def to_geojson(self) -> dict[str, Any]:
        """The map's geometry as a GeoJSON mapping."""
        return geometry_to_geojson(self.geometry)

    @property
    def grid(self) -> Grid:
        """The walls and their grid index as the compiled kernels take them (see
        :mod:`rlutf._kernels`)."""
        ix = self.index
        return (
            self.segments,
            ix.origin[0],
            ix.origin[1],
            ix.cell_size,
            ix.nx,
            ix.ny,
            ix.cell_start,
            ix.cell_walls,
        )

    def derived(self, key: str, make: Callable[[Map], T]) -> T:
        """A structure derived from the map (a distance field, say), made on first use and kept
        with the map, so that it is made once per map version."""
        found = self._derived.get(key)
        if found is None:
            found = make(self)
            self._derived[key] = found
        return cast(T, found)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(minx, miny, maxx, maxy)`` of the free space."""
        b = self.geometry.bounds
        return (float(b[0]), float(b[1]), float(b[2]), float(b[3]))

    def contains_point(self, x: float, y: float) -> bool:
        """Whether the point ``(x, y)`` lies in the free space (walls excluded); for one point,
        cheaper than :meth:`contains`."""
        return bool(shapely.contains_xy(self.geometry, x, y))

    def contains(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each point ``(K, 2)`` lies in the free space (walls excluded)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return np.asarray(shapely.contains_xy(self.geometry, pts[:, 0], pts[:, 1]), dtype=bool)


def _segments_of(geom: Polygon | MultiPolygon) -> FloatArray:
    polys = [geom] if isinstance(geom, Polygon) else list(geom.geoms)
    parts: list[FloatArray] = []
    for p in polys:
        # Free space on the left of every wall: the ray caster skips walls seen from behind.
        oriented = orient(p, sign=1.0)
        for ring in (oriented.exterior, *oriented.interiors):
            xy = np.asarray(ring.coords, dtype=np.float64)[:, :2]
            seg = np.hstack([xy[:-1], xy[1:]])
            keep = (seg[:, 0] != seg[:, 2]) | (seg[:, 1] != seg[:, 3])
            parts.append(seg[keep])
    return np.ascontiguousarray(np.vstack(parts))
