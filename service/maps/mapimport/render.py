"""Draw a polygon map to a PNG: free space filled, walls drawn, axes and a scale bar in metres.

Uses matplotlib's Agg canvas directly (no pyplot, no global state), so it is safe in threads
and on machines without a display.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import shapely
import shapely.geometry
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath
from numpy.typing import ArrayLike
from shapely.geometry import MultiPolygon, Polygon

from rlutf.errors import MapError
from rlutf.map import geometry_from_geojson
from service.maps.mapimport.errors import MapFileError, MapImportError

FREE_COLOUR = "#dcebf7"
WALL_COLOUR = "#1f2a36"
POSE_COLOUR = "#d1495b"
ADDED_COLOUR = "#e4572e"
REMOVED_COLOUR = "#2e86ab"


def _as_geometry(source: Polygon | MultiPolygon | Mapping[str, Any]) -> Polygon | MultiPolygon:
    if isinstance(source, Polygon | MultiPolygon):
        return source
    geometry = source.get("geometry", source)
    if not isinstance(geometry, Mapping):
        raise MapImportError("render: 'geometry' must be a GeoJSON Polygon or MultiPolygon")
    try:
        return geometry_from_geojson(geometry)
    except MapError as err:
        raise MapImportError(f"render: {err}") from err


def _path_of(geom: Polygon | MultiPolygon) -> MplPath:
    """One compound path; rings oriented so that holes stay empty under nonzero filling."""
    oriented = shapely.orient_polygons(geom)
    vertices: list[np.ndarray[Any, Any]] = []
    codes: list[np.ndarray[Any, Any]] = []
    for poly in shapely.get_parts(oriented):
        for ring in (poly.exterior, *poly.interiors):
            xy = np.asarray(ring.coords)[:, :2]
            code = np.full(len(xy), MplPath.LINETO, dtype=np.uint8)
            code[0], code[-1] = MplPath.MOVETO, MplPath.CLOSEPOLY
            vertices.append(xy)
            codes.append(code)
    return MplPath(np.vstack(vertices), np.concatenate(codes))


def _scale_length(span: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) near a fifth of ``span``."""
    target = max(span / 5.0, 1e-9)
    power = 10.0 ** math.floor(math.log10(target))
    return next((m * power for m in (5.0, 2.0, 1.0) if m * power <= target), power)


def render_map(
    source: Polygon | MultiPolygon | Mapping[str, Any],
    out: str | Path | BinaryIO,
    *,
    title: str | None = None,
    poses: ArrayLike | None = None,
    changes: Sequence[Mapping[str, Any]] = (),
    width_inches: float = 10.0,
    dpi: int = 150,
) -> None:
    """Render a map to PNG.

    Args:
        source: a shapely geometry, a GeoJSON geometry mapping, or a wire Map dict (with
            ``map_id``, ``version`` and ``geometry``).
        out: the PNG's path or a binary stream.
        title: the title; by default the map id and version (when known), area and walls.
        poses: optional ``(K, 2)`` or ``(K, 3)`` map-frame positions drawn as a trajectory.
        changes: MapHealth changes drawn over the map: ``added`` areas filled red,
            ``removed`` walls as thick blue lines.
        width_inches: figure width; the height follows the map's aspect ratio.
        dpi: resolution.

    Raises:
        MapImportError: the source is not a polygonal map.
        MapFileError: the PNG cannot be written.
    """
    geom = _as_geometry(source)
    if geom.is_empty:
        raise MapImportError("render: the map is empty")
    x0, y0, x1, y1 = geom.bounds
    if not math.isfinite((x1 - x0) * (y1 - y0)):  # finite corners, an extent past a float
        raise MapImportError(
            f"render: the map spans {x1 - x0:g} m x {y1 - y0:g} m, more than a float holds "
            "(are the coordinates in metres?); no storage takes it"
        )
    segments = [
        np.asarray(ring.coords)[:, :2]
        for poly in shapely.get_parts(geom)
        for ring in (poly.exterior, *poly.interiors)
    ]
    walls = sum(len(s) - 1 for s in segments)
    if title is None:
        head = "map"
        if isinstance(source, Mapping) and "map_id" in source:
            head = f"{source['map_id']} v{source.get('version', '?')}"
        title = f"{head}: free area {geom.area:.1f} m\u00b2, {walls} walls"
    x0, y0, x1, y1 = geom.bounds
    span_x, span_y = max(x1 - x0, 1e-6), max(y1 - y0, 1e-6)
    height = min(max(width_inches * span_y / span_x, 3.0), 3.0 * width_inches) + 0.8
    fig = Figure(figsize=(width_inches, height), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor("#9aa3ad")
    ax.add_patch(PathPatch(_path_of(geom), facecolor=FREE_COLOUR, edgecolor="none"))
    ax.add_collection(LineCollection(segments, colors=WALL_COLOUR, linewidths=0.8))
    if poses is not None:
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise MapImportError(f"render: poses must be (K, 2) or (K, 3), got {p.shape}")
        ax.plot(p[:, 0], p[:, 1], color=POSE_COLOUR, linewidth=0.8, marker=".", markersize=2)
    _draw_changes(ax, changes)
    margin = 0.03 * max(span_x, span_y)
    ax.set_xlim(x0 - margin, x1 + margin)
    ax.set_ylim(y0 - margin, y1 + margin)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    length = _scale_length(span_x)
    bar_x = x1 + margin * 0.5 - length
    bar_y = y0 - margin * 0.5
    ax.plot([bar_x, bar_x + length], [bar_y, bar_y], color="black", linewidth=3)
    ax.text(
        bar_x + 0.5 * length, bar_y, f"{length:g} m", ha="center", va="bottom",
        bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.7, "pad": 1.0},
    )  # fmt: skip
    fig.tight_layout()
    try:
        fig.savefig(out, format="png")
    except OSError as err:
        raise MapFileError(f"cannot write '{out}': {err.strerror or err}") from err


def _draw_changes(ax: Any, changes: Sequence[Mapping[str, Any]]) -> None:
    """MapHealth changes over the map, with a legend when there are any."""
    labels: set[str] = set()
    for change in changes:
        geom = shapely.geometry.shape(change["geometry"])
        kind = change["kind"]
        label = None if kind in labels else kind
        labels.add(kind)
        for part in shapely.get_parts(geom):
            if kind == "added":
                ax.add_patch(
                    PathPatch(_path_of(part), facecolor=ADDED_COLOUR, edgecolor=ADDED_COLOUR,
                              alpha=0.6, label=label)
                )  # fmt: skip
            else:
                xy = np.asarray(part.coords)
                ax.plot(xy[:, 0], xy[:, 1], color=REMOVED_COLOUR, linewidth=3.5, label=label)
            label = None
    if labels:
        ax.legend(loc="upper right", fontsize=8)
