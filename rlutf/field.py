"""A distance field over a map, and the wide search that uses it.

Comparing ranges beam by beam (the polar area, the refinement) only sees errors smaller than the
distance between walls: from a pose off by half a metre most beams hit the wrong wall, or none,
and the comparison goes flat. The distance from each scan point to the nearest wall still falls
smoothly as the pose nears the right one, whichever wall the point belongs to. So a pose given
with a wide uncertainty (an operator's click on a map, the first scan after a handover, a robot
that was lost) is searched first on a grid of poses scored by the distance field (as
correlative scan matchers do: Olson 2009; Cartographer's real-time correlative matcher), and
the few best distinct poses are handed to the fine comparison and the refinement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rlutf.map import Map

FloatArray = NDArray[np.float64]

#: Cell side of the distance field, metres.
FIELD_RESOLUTION = 0.05
#: Distances are exact up to this, metres, and truncated to it beyond.
FIELD_TRUNCATION = 0.5


@dataclass(frozen=True, eq=False)
class DistanceField:
    """Distances from cell centres to the nearest wall, truncated.

    Attributes:
        values: ``(H, W)`` float32 distances, metres; row ``r`` column ``c`` is the cell whose
            centre is ``origin + ((c + 0.5), (r + 0.5)) * resolution``.
        origin: ``(x, y)`` corner of cell ``(0, 0)``, metres.
        resolution: cell side, metres.
        truncation: the largest distance stored, metres.
    """

    values: NDArray[np.float32]
    origin: tuple[float, float]
    resolution: float
    truncation: float

    @classmethod
    def of(
        cls,
        world: Map,
        resolution: float = FIELD_RESOLUTION,
        truncation: float = FIELD_TRUNCATION,
    ) -> DistanceField:
        """The field of ``world`` over its bounds plus ``truncation``."""
        from rlutf import _grid

        minx, miny, maxx, maxy = world.bounds
        x0, y0 = minx - truncation, miny - truncation
        width = math.ceil((maxx - minx + 2 * truncation) / resolution)
        height = math.ceil((maxy - miny + 2 * truncation) / resolution)
        values = _grid.distance_field(world.segments, x0, y0, resolution, width, height, truncation)
        values.flags.writeable = False
        return cls(values, (x0, y0), resolution, truncation)

    def at(self, points: FloatArray) -> FloatArray:
        """``(n,)`` distances at ``(n, 2)`` points (nearest cell; ``truncation`` off the field)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        row = np.floor((p[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        height, width = self.values.shape
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        out = np.full(len(p), self.truncation)
        out[inside] = self.values[row[inside], col[inside]]
        return out


def distance_field(world: Map) -> DistanceField:
    """The map's distance field, made on first use and kept with the map."""
    return world.derived("distance_field", DistanceField.of)


@dataclass(frozen=True)
class WideSearch:
    """Parameters of :func:`wide_search`.

    Attributes:
        step: position step of the grid of poses, metres.
        heading_step_max: largest heading step, radians; the step is the one that moves the
            scan's far points (90th percentile of the ranges) by about ``step``.
        cap: each point's squared distance counts at most ``cap^2`` (points on things that are
            not on the map), metres.
        keep: distinct best poses returned.
        max_points: the scan is thinned to at most this many points.
        max_turns: at most this many heading steps on each side of the pose's heading (the
            step grows past the one above for scans with far returns: a scan whose ranges are
            1e5 m would otherwise be searched over hundreds of thousands of headings).
    """

    step: float = 0.1
    heading_step_max: float = math.radians(2.0)
    cap: float = 0.3
    keep: int = 6
    max_points: int = 180
    max_turns: int = 1024


def wide_search(
    world: Map,
    centre: FloatArray,
    points: FloatArray,
    radius: float,
    heading_radius: float,
    settings: WideSearch,
) -> tuple[list[tuple[FloatArray, float]], int]:
    """The best distinct poses within ``radius`` and ``heading_radius`` of ``centre``.

    Args:
        world: the map.
        centre: ``(3,)`` the pose given.
        points: ``(n, 2)`` the scan's points in the base frame.
        radius: metres.
        heading_radius: radians.
        settings: the grid and the score.

    Returns:
        Up to ``settings.keep`` ``(pose, score)`` pairs, best (lowest mean capped squared
        distance, m^2) first, at least two grid steps apart in position or heading; and the
        number of poses scored.
    """
    from rlutf import _grid

    field = distance_field(world)
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) > settings.max_points:
        pts = pts[np.linspace(0, len(pts) - 1, settings.max_points).round().astype(np.int64)]
    far = float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 90)) if len(pts) else 1.0
    step = settings.step
    heading_step = min(settings.heading_step_max, step / max(far, step))
    half = math.ceil(radius / step)
    axis = np.arange(-half, half + 1) * step
    gx, gy = np.meshgrid(axis, axis)
    offsets = np.column_stack([gx.ravel(), gy.ravel()])
    offsets = offsets[np.hypot(offsets[:, 0], offsets[:, 1]) <= radius + 0.5 * step]
    turns = math.ceil(heading_radius / heading_step)
    if turns > settings.max_turns:
        turns = settings.max_turns
        heading_step = heading_radius / turns
    headings = np.arange(-turns, turns + 1) * heading_step
    scores = _grid.score_field_grid(
        float(centre[0]),
        float(centre[1]),
        float(centre[2]),
        np.ascontiguousarray(offsets),
        headings,
        np.ascontiguousarray(pts[:, 0]),
        np.ascontiguousarray(pts[:, 1]),
        field.values,
        field.origin[0],
        field.origin[1],
        field.resolution,
        settings.cap,
    )
    order = np.argsort(scores, axis=None, kind="stable")
    picked: list[tuple[int, int]] = []
    out: list[tuple[FloatArray, float]] = []
    for flat in order[: 50 * settings.keep * settings.keep + 1000]:
        h, j = divmod(int(flat), len(offsets))
        near = any(
            abs(h - ph) <= 2 and float(np.hypot(*(offsets[j] - offsets[pj]))) <= 2.0 * step + 1e-9
            for ph, pj in picked
        )
        if near:
            continue
        picked.append((h, j))
        pose = np.array(
            [centre[0] + offsets[j, 0], centre[1] + offsets[j, 1], centre[2] + headings[h]]
        )
        out.append((pose, float(scores[h, j])))
        if len(out) >= settings.keep:
            break
    return out, int(scores.size)
