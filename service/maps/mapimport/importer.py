"""Occupancy grid to wire Map: the functions behind ``rlutf map import`` and ``map build``.

The result is a plain dict in the wire layout of WIRE.md (``map_id``, ``version``,
``frame_id``, ``geometry``), already checked with :meth:`rlutf.map.Map.from_shapely`, plus a
report of what was kept and dropped for the user.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlutf.errors import MapError
from rlutf.map import Map, geometry_to_geojson
from service.maps.mapimport.errors import MapImportError
from service.maps.mapimport.grid import OccupancyGrid, load_grid
from service.maps.mapimport.polygonize import (
    DEFAULT_MIN_AREA,
    DEFAULT_MIN_HOLE_AREA,
    ComponentSpec,
    Polygonized,
    polygonal,
    polygonize,
)

_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
#: ``surface_offset`` of maps built from scans, in cells: a surface hit lies half a cell deep in
#: its cell on average (measured on the CARMEN logs: ranges cast on a map traced at the cell
#: edges were 3.4 cm short at 5 cm cells); 0.4 keeps a one-cell obstacle 0.2 cells thick.
BUILT_SURFACE_CELLS = 0.4


@dataclass(frozen=True, eq=False)
class ImportResult:
    """A map ready to put on the bus, and how it was made.

    Attributes:
        map: the wire Map dict: ``map_id``, ``version``, ``frame_id`` ``"map"``, ``geometry``.
        report: human-readable lines: the grid, the components kept and dropped, the
            obstacles filled, and the polygon area against the free cells.
        polygons: the geometry and the details of the selection.
        grid: the occupancy grid it came from.
    """

    map: dict[str, Any]
    report: tuple[str, ...]
    polygons: Polygonized = field(repr=False)
    grid: OccupancyGrid = field(repr=False)


def map_id_from_name(name: str) -> str:
    """A valid map id (``[A-Za-z0-9_-]{1,64}``) from a file name: other characters become ``-``.

    Raises:
        MapImportError: nothing usable is left.
    """
    cleaned = re.sub(r"[^A-Za-z0-9_-]+", "-", name).strip("-")[:64]
    if not cleaned:
        raise MapImportError(f"map_id: cannot make a map id from {name!r}; give one")
    return cleaned


def parse_component(text: str) -> ComponentSpec:
    """Parse the CLI's ``--component``: ``all``, an index (``3``) or a point (``12.5,-3``).

    Raises:
        MapImportError: none of these.
    """
    value = text.strip()
    if value.lower() == "all":
        return "all"
    if value.lstrip("+").isdigit():
        return int(value)
    parts = value.split(",")
    if len(parts) == 2:
        try:
            point = (float(parts[0]), float(parts[1]))
        except ValueError:
            pass
        else:
            if all(map(math.isfinite, point)):  # nan or inf is no place on a map
                return point
    raise MapImportError(
        f"component: expected 'all', an index like 0 or a point like 12.5,-3.0; got {text!r}"
    )


def grid_to_map(
    grid: OccupancyGrid,
    *,
    map_id: str,
    version: int = 1,
    component: ComponentSpec = None,
    min_area: float = DEFAULT_MIN_AREA,
    min_hole_area: float = DEFAULT_MIN_HOLE_AREA,
    simplify: float | None = None,
    surface_offset: float = 0.0,
) -> ImportResult:
    """Polygonize a grid into a wire Map dict.

    Args:
        grid: the occupancy grid.
        map_id: the map id, ``[A-Za-z0-9_-]{1,64}``.
        version: the map version, a non-negative integer.
        component: which free component to keep (see :func:`polygonize`).
        min_area: with ``component="all"``, smaller components are dropped (square metres).
        min_hole_area: smaller obstacles are filled in (square metres).
        simplify: Douglas-Peucker tolerance in metres; None for half a cell.
        surface_offset: move the walls this far into the occupied cells, metres (the free
            space grows by it). The traced boundary runs along the edges of the free cells,
            but a surface that a scanner hit lies inside its cell, half a cell deep on
            average: maps built from scans (:data:`BUILT_SURFACE_CELLS`) set it, so that ranges
            cast on the map are not short by half a cell.

    Returns:
        The map and the report.

    Raises:
        MapImportError: bad id or version, no free space, unknown component, or a geometry
            that fails the map validation (a bug: the message says why).
    """
    if not _ID.match(map_id):
        raise MapImportError(f"map_id: must match [A-Za-z0-9_-]{{1,64}}, got {map_id!r}")
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise MapImportError(f"version: must be a non-negative integer, got {version!r}")
    result = polygonize(
        grid,
        component=component,
        min_area=min_area,
        min_hole_area=min_hole_area,
        simplify=simplify,
    )
    if not 0.0 <= surface_offset < 0.5 * grid.resolution:
        raise MapImportError(
            f"surface_offset: must be within [0, half a cell = {0.5 * grid.resolution:g} m), "
            f"got {surface_offset!r}"
        )
    geometry = result.geometry
    if surface_offset > 0.0:
        # Mitred joins keep square corners square; under half a cell, an obstacle one cell
        # thick keeps some thickness, so no two free regions merge.
        grown = geometry.buffer(surface_offset, join_style="mitre", mitre_limit=2.0)
        geometry = polygonal(grown)
    try:
        checked = Map.from_shapely(geometry)
    except MapError as err:
        raise MapImportError(f"the traced map is not a valid map: {err}") from err
    wire = {
        "map_id": map_id,
        "version": version,
        "frame_id": "map",
        "geometry": geometry_to_geojson(checked.geometry),
    }
    report = (f"map {map_id} version {version}", *result.report(grid))
    return ImportResult(wire, report, result, grid)


def import_grid(
    yaml_path: str | Path,
    *,
    map_id: str | None = None,
    version: int = 1,
    component: ComponentSpec = None,
    min_area: float = DEFAULT_MIN_AREA,
    min_hole_area: float = DEFAULT_MIN_HOLE_AREA,
    simplify: float | None = None,
) -> ImportResult:
    """Import a ROS map_server map (YAML and image) as a wire Map dict.

    Args:
        yaml_path: the map's YAML file.
        map_id: the map id; by default the YAML file's name without its suffix.
        version: the map version.
        component: which free component to keep: None for the largest, an index into the
            report's listing, a map-frame point ``(x, y)`` inside it, or ``"all"``.
        min_area: with ``"all"``, smaller components are dropped (square metres).
        min_hole_area: smaller obstacles are filled in (square metres).
        simplify: Douglas-Peucker tolerance in metres, at most the resolution; None for half
            a cell.

    Returns:
        The map and the report (its first lines name the source files).

    Raises:
        MapImportError: missing or unreadable files, bad YAML keys, no free space, unknown
            component.
    """
    path = Path(yaml_path)
    grid = load_grid(path)
    result = grid_to_map(
        grid,
        map_id=map_id if map_id is not None else map_id_from_name(path.stem),
        version=version,
        component=component,
        min_area=min_area,
        min_hole_area=min_hole_area,
        simplify=simplify,
    )
    return ImportResult(
        result.map, (f"source: {path}", *result.report), result.polygons, result.grid
    )
