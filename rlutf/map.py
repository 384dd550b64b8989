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
from rlutf.simplify import simplify_rings

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
    from rlutf import _grid

    x0 = float(min(segments[:, 0].min(), segments[:, 2].min()))
    y0 = float(min(segments[:, 1].min(), segments[:, 3].min()))
    x1 = float(max(segments[:, 0].max(), segments[:, 2].max()))
    y1 = float(max(segments[:, 1].max(), segments[:, 3].max()))
    nx = max(math.ceil((x1 - x0) / cell_size), 1)
    ny = max(math.ceil((y1 - y0) / cell_size), 1)
    # Compiled: a Python list per cell cost time and memory in proportion to the map's area
    # (a 2 km square: 8 s and 340 MB), and a loop per wall 0.6 s for 40,000 walls.
    start, flat = _grid.wall_cells(segments, x0, y0, cell_size, nx, ny)
    return WallIndex((x0, y0), cell_size, nx, ny, start, flat)


@dataclass(frozen=True)
class MapLimits:
    """What a map may cost, checked on the raw coordinates before anything is built.

    The structures made from a map cost time and memory in proportion to the area of its
    bounding box (the wall index, the distance field of the wide search at 5 cm, the
    relocalization's search grid at 10 cm: about 3 kB per square metre together) and to its
    vertex count (validation, the walls), not to its size in bytes: a 144-byte square of 2 km
    is as costly as a 2 km site. ``None`` is no limit.

    Attributes:
        max_area: largest bounding box area, square metres.
        max_vertices: most positions over all rings.
    """

    max_area: float | None = None
    max_vertices: int | None = None

    def check(self, bounds: tuple[float, float, float, float], vertices: int) -> None:
        """Raise :class:`MapError` when a map of these bounds and vertex count is over.

        Raises:
            MapError: naming the figure and the limit.
        """
        if self.max_vertices is not None and vertices > self.max_vertices:
            raise MapError(
                f"coordinates: {vertices} vertices, more than the limit of {self.max_vertices} "
                "(setting max_map_vertices)"
            )
        if not all(map(math.isfinite, bounds)):
            return  # geometry_from_geojson names the non-finite coordinate
        width, height = bounds[2] - bounds[0], bounds[3] - bounds[1]
        # Finite coordinates may still span more than a float holds (1e308 and -1e308), or an
        # area that overflows: infinite, and over any limit.
        if self.max_area is not None and width * height > self.max_area:
            raise MapError(
                f"coordinates: the map spans {width:g} m x {height:g} m = {width * height:g} m2, "
                f"more than the limit of {self.max_area:g} m2 (setting max_map_area; are the "
                "coordinates in metres?)"
            )


def raw_extent(geometry: Mapping[str, Any]) -> tuple[tuple[float, float, float, float], int]:
    """Bounds and vertex count of a GeoJSON mapping's positions, before any validation: what
    :meth:`MapLimits.check` is given for a map that is not built yet."""
    kind = geometry.get("type")
    coords = geometry.get("coordinates")
    polygons = [coords] if kind == "Polygon" else coords if kind == "MultiPolygon" else None
    rings: list[FloatArray] = []
    for poly in polygons if isinstance(polygons, Sequence) else []:
        for ring in poly if isinstance(poly, Sequence) and not isinstance(poly, str) else []:
            try:
                arr = np.asarray(ring, dtype=np.float64)
            except (TypeError, ValueError):
                continue  # geometry_from_geojson says what is wrong
            if arr.ndim == 2 and arr.shape[1] >= 2 and len(arr):
                rings.append(arr[:, :2])
    if not rings:
        return (0.0, 0.0, 0.0, 0.0), 0
    lo = np.min([r.min(axis=0) for r in rings], axis=0)
    hi = np.max([r.max(axis=0) for r in rings], axis=0)
    count = sum(len(r) for r in rings)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), count


@dataclass(frozen=True, eq=False)
class Map:
    """A validated polygon map.

    Attributes:
        geometry: free space, a shapely ``Polygon`` or ``MultiPolygon`` in metres.
        segments: ``(M, 4)`` walls as ``x1, y1, x2, y2`` rows, metres, each directed so that the
            free space is on its left (outer rings counter-clockwise, holes clockwise).
        cell_size: side of a cell of the wall index, metres.
        wall_start: ``(M,)`` wall start points as complex numbers ``x + iy``.
        wall_direction: ``(M,)`` wall vectors (end minus start) as complex numbers.
        wall_length: ``(M,)`` wall lengths, metres.
    """

    geometry: Polygon | MultiPolygon
    segments: FloatArray = field(repr=False)
    cell_size: float = DEFAULT_CELL_SIZE
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
        x0, y0, x1, y1 = geom.bounds
        width, height = x1 - x0, y1 - y0
        if not math.isfinite(width * height):  # finite coordinates, an extent that overflows
            raise MapError(
                f"geometry: the map spans {width:g} m x {height:g} m, more than a float holds "
                "(are the coordinates in metres?)"
            )
        if not geom.is_valid:
            raise MapError(f"geometry: invalid polygon: {explain_validity(geom)}")
        if geom.area <= 0.0:
            raise MapError("geometry: the map has zero area")
        if not cell_size > 0:
            raise MapError(f"cell_size: must be positive, got {cell_size}")
        segments = _segments_of(geom)
        shapely.prepare(geom)
        return cls(geom, segments, cell_size)

    def __reduce__(self) -> tuple[Callable[..., Map], tuple[Any, ...]]:
        """Pickled as its geometry, walls and cell size: the rest is made again (the wall
        vectors) or on first use (the index, derived structures), and the geometry prepared,
        so that a map validated in another process costs little to send and to take in."""
        return _restored, (self.geometry, self.segments, self.cell_size)

    @classmethod
    def from_geojson(
        cls,
        geometry: Mapping[str, Any],
        *,
        cell_size: float = DEFAULT_CELL_SIZE,
        limits: MapLimits | None = None,
    ) -> Map:
        """Build and validate a map from a GeoJSON ``Polygon``/``MultiPolygon`` mapping.

        Args:
            geometry: the mapping, metres.
            cell_size: side of a cell of the wall index, metres.
            limits: checked on the raw positions before anything is built.

        Raises:
            MapError: invalid, or over ``limits``.
        """
        if limits is not None:
            limits.check(*raw_extent(geometry))
        return cls.from_shapely(geometry_from_geojson(geometry), cell_size=cell_size)

    @property
    def index(self) -> WallIndex:
        """Grid index of the walls, for range-limited queries; made on first use, so that a
        process that only validates maps never pays for it."""
        return self.derived("wall_index", lambda w: _build_index(w.segments, w.cell_size))

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
        """``(minx, miny, maxx, maxy)`` of the free space (computed once: every scan asks)."""
        found = self._derived.get("bounds")
        if found is None:
            b = self.geometry.bounds
            found = self._derived["bounds"] = (float(b[0]), float(b[1]), float(b[2]), float(b[3]))
        return cast(tuple[float, float, float, float], found)

    def contains_point(self, x: float, y: float) -> bool:
        """Whether the point ``(x, y)`` lies in the free space (walls excluded); for one point,
        cheaper than :meth:`contains`."""
        return bool(shapely.contains_xy(self.geometry, x, y))

    def contains(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each point ``(K, 2)`` lies in the free space (walls excluded)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return np.asarray(shapely.contains_xy(self.geometry, pts[:, 0], pts[:, 1]), dtype=bool)


def _restored(geom: Polygon | MultiPolygon, segments: FloatArray, cell_size: float) -> Map:
    """A :class:`Map` unpickled (see :meth:`Map.__reduce__`): validated where it was made."""
    shapely.prepare(geom)
    return Map(geom, segments, cell_size)


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


#: :func:`coarse_map` keeps the map itself when simplifying leaves more than this share of its
#: walls: a drawn map (straight walls; the simulated buildings keep 84 to 94 % of theirs at
#: 7 cm) rather than one traced from a grid (Nav2's depot and sandbox and the intel and aces
#: maps built from their logs keep 22 to 32 %).
COARSE_KEEP = 0.5


def coarse_map(world: Map, tolerance: float) -> Map:
    """``world`` with its walls simplified at ``tolerance`` metres (Douglas-Peucker, topology
    preserved), made once per map and tolerance; ``world`` itself when that keeps more than
    :data:`COARSE_KEEP` of its walls (a drawn map) or does not give a valid map.

    A map traced from a grid has walls in small steps and bumps of about a cell; the range
    refinement from a start a few centimetres off stops in the small local minima these make,
    and the simplified walls have fewer (the localizer tracks on them and takes its answer
    from the map itself, :mod:`rlutf.localizer`).
    """
    if not tolerance > 0:
        return world
    return world.derived(f"coarse:{tolerance!r}", lambda w: _simplified(w, tolerance))


def _simplified(world: Map, tolerance: float) -> Map:
    geom = simplify_rings(world.geometry, tolerance)
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    parts = [g for g in shapely.get_parts(geom) if isinstance(g, Polygon) and not g.is_empty]
    if not parts:
        return world
    poly = parts[0] if len(parts) == 1 else MultiPolygon(parts)
    try:
        coarse = Map.from_shapely(poly, cell_size=world.cell_size)
    except MapError:
        return world
    return world if len(coarse.segments) > COARSE_KEEP * len(world.segments) else coarse
