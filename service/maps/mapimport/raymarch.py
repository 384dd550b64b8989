"""Rays on occupancy grids: an exact, vectorised cell traversal and a grid ray marcher.

:func:`traverse` (Amanatides and Woo, 1987) walks many beams through a grid in lock-step; the
map builder counts the cells beams pass with it, and :func:`march_rays` finds the first wall,
which is what polygon ray casting on an imported map must reproduce.

Coordinates are in cell units of a grid whose cell ``(row, col)`` covers
``[col, col + 1) x [row, row + 1)``; distances along a beam are in the same units.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.maps.mapimport.grid import OccupancyGrid

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def traverse(
    origins: FloatArray,
    directions: FloatArray,
    t_stop: FloatArray,
    shape: tuple[int, int],
    blocked: BoolArray | None = None,
) -> Iterator[tuple[IntArray, IntArray, FloatArray]]:
    """Walk every beam cell by cell, all beams in lock-step.

    Each beam visits each cell it crosses exactly once, in order. A beam ends at the first cell
    it enters at or beyond ``t_stop``, on leaving the grid, or after a cell that ``blocked``
    marks (that cell is still yielded). Beams whose origin is outside the grid visit nothing.

    Args:
        origins: ``(B, 2)`` beam origins ``(x, y)``, cell units.
        directions: ``(B, 2)`` unit directions.
        t_stop: ``(B,)`` distance at which each beam ends, cell units.
        shape: ``(rows, cols)`` of the grid.
        blocked: optional ``(rows * cols,)`` flat mask of cells that end a beam.

    Yields:
        ``(beam, flat, t_enter)``: for the beams still walking, their index, the flat index
        ``row * cols + col`` of the cell they are in, and the distance at which they entered
        it (0 for the origin's cell).
    """
    rows, cols = shape
    ox, oy = origins[:, 0], origins[:, 1]
    dx, dy = directions[:, 0], directions[:, 1]
    ix = np.floor(ox).astype(np.int64)
    iy = np.floor(oy).astype(np.int64)
    beam = np.flatnonzero((ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)).astype(np.int64)
    ix, iy, ox, oy, dx, dy = ix[beam], iy[beam], ox[beam], oy[beam], dx[beam], dy[beam]
    stop = t_stop[beam]
    step_x = np.where(dx > 0, 1, -1).astype(np.int64)
    step_y = np.where(dy > 0, 1, -1).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta_x = np.where(dx != 0, 1.0 / np.abs(dx), np.inf)
        delta_y = np.where(dy != 0, 1.0 / np.abs(dy), np.inf)
        next_x = np.where(dx != 0, (ix + (dx > 0) - ox) / dx, np.inf)
        next_y = np.where(dy != 0, (iy + (dy > 0) - oy) / dy, np.inf)
    t_enter = np.zeros(len(beam))
    while len(beam):
        flat = iy * cols + ix
        yield beam, flat, t_enter
        use_x = next_x < next_y
        t_enter = np.where(use_x, next_x, next_y)
        ix = ix + np.where(use_x, step_x, 0)
        iy = iy + np.where(use_x, 0, step_y)
        next_x = np.where(use_x, next_x + delta_x, next_x)
        next_y = np.where(use_x, next_y, next_y + delta_y)
        keep = (t_enter < stop) & (ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)
        if blocked is not None:
            keep &= ~blocked[flat]
        beam, ix, iy, t_enter = beam[keep], ix[keep], iy[keep], t_enter[keep]
        next_x, next_y, delta_x, delta_y = next_x[keep], next_y[keep], delta_x[keep], delta_y[keep]
        step_x, step_y, stop = step_x[keep], step_y[keep], stop[keep]


def march_rays(
    grid: OccupancyGrid,
    poses: ArrayLike,
    angles: ArrayLike,
    max_range: float,
    *,
    free: BoolArray | None = None,
) -> FloatArray:
    """Exact ranges from poses to the first non-free cell of a grid (its edge, not centre).

    Cells outside the grid count as walls, like the border that :mod:`polygonize` adds.

    Args:
        grid: the grid (its placement and resolution; its free mask unless ``free`` is given).
        poses: ``(K, 3)`` map-frame poses ``(x, y, theta)``.
        angles: ``(N,)`` beam angles relative to each pose's heading, radians.
        max_range: walls farther than this (metres) give ``inf``.
        free: optional ``(rows, cols)`` free mask to use instead of ``grid.free``.

    Returns:
        ``(K, N)`` ranges, metres; 0 for a pose in a non-free cell.
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(angles, dtype=np.float64).reshape(-1)
    mask = grid.free if free is None else free
    blocked = ~np.pad(mask, 1, constant_values=False)
    local = grid.to_local(p[:, :2]) / grid.resolution + 1.0
    heading = (p[:, 2] - grid.origin[2])[:, None] + a[None, :]
    origins = np.repeat(local, len(a), axis=0)
    directions = np.column_stack([np.cos(heading).ravel(), np.sin(heading).ravel()])
    out = np.full(len(origins), np.inf)
    stop = np.full(len(origins), max_range / grid.resolution)
    for beam, flat, t_enter in traverse(origins, directions, stop, blocked.shape, blocked.ravel()):
        hit = blocked.ravel()[flat]
        out[beam[hit]] = t_enter[hit] * grid.resolution
    out[out > max_range] = np.inf
    return out.reshape(len(p), len(a))
