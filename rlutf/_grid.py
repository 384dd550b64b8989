"""Compiled distance fields and scores of scans on grids (see :mod:`rlutf.field`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def distance_field(
    segments: np.ndarray, fx0: float, fy0: float, resolution: float, width: int, height: int,
    truncation: float,
) -> np.ndarray:  # fmt: skip
    """``(height, width)`` distances from cell centres to the nearest wall, truncated."""
    field = np.full((height, width), truncation, dtype=np.float32)
    for w in range(segments.shape[0]):
        ax = segments[w, 0]
        ay = segments[w, 1]
        ex = segments[w, 2] - ax
        ey = segments[w, 3] - ay
        ee = ex * ex + ey * ey
        c0 = max(int(math.floor((min(ax, ax + ex) - truncation - fx0) / resolution)), 0)
        c1 = min(int(math.floor((max(ax, ax + ex) + truncation - fx0) / resolution)), width - 1)
        r0 = max(int(math.floor((min(ay, ay + ey) - truncation - fy0) / resolution)), 0)
        r1 = min(int(math.floor((max(ay, ay + ey) + truncation - fy0) / resolution)), height - 1)
        for r in range(r0, r1 + 1):
            py = fy0 + (r + 0.5) * resolution - ay
            for c in range(c0, c1 + 1):
                px = fx0 + (c + 0.5) * resolution - ax
                s = (px * ex + py * ey) / ee if ee > 0.0 else 0.0
                s = min(max(s, 0.0), 1.0)
                qx = px - s * ex
                qy = py - s * ey
                # Most cells of a short wall's box are nearer another wall already: skip the
                # square root there (the margin keeps the result bit for bit what it was).
                cur = float(field[r, c])
                if qx * qx + qy * qy >= cur * cur * 1.0000001 + 1e-12:
                    continue
                field[r, c] = min(field[r, c], math.hypot(qx, qy))
    return field


@njit(cache=True, nogil=True)
def score_field_grid(
    cx: float,
    cy: float,
    ct: float,
    offsets_xy: np.ndarray,
    headings: np.ndarray,
    px: np.ndarray,
    py: np.ndarray,
    field: np.ndarray,
    fx0: float,
    fy0: float,
    resolution: float,
    cap: float,
) -> np.ndarray:
    """Mean capped squared distance field at the scan's points for every pose of a grid.

    The poses are ``(cx, cy) + offsets_xy[j]`` with heading ``ct + headings[h]``; the scan's
    points are ``(px, py)`` in the base frame. Points off the field count as ``cap``. Returns
    ``(H, J)`` scores (metres squared)."""
    height, width = field.shape
    n = len(px)
    out = np.empty((len(headings), offsets_xy.shape[0]))
    wx = np.empty(n)
    wy = np.empty(n)
    cap2 = cap * cap
    inv = 1.0 / resolution
    for h in range(len(headings)):
        c = math.cos(ct + headings[h])
        s = math.sin(ct + headings[h])
        for i in range(n):
            wx[i] = (c * px[i] - s * py[i] + cx - fx0) * inv
            wy[i] = (s * px[i] + c * py[i] + cy - fy0) * inv
        for j in range(offsets_xy.shape[0]):
            ox = offsets_xy[j, 0] * inv
            oy = offsets_xy[j, 1] * inv
            total = 0.0
            for i in range(n):
                col = int(math.floor(wx[i] + ox))
                row = int(math.floor(wy[i] + oy))
                if 0 <= col < width and 0 <= row < height:
                    d = float(field[row, col])
                    total += min(d * d, cap2)
                else:
                    total += cap2
            out[h, j] = total / n
    return out


@njit(cache=True, nogil=True)
def _visit_wall_cells(
    segments: np.ndarray, x0: float, y0: float, cell: float, nx: int,
    ny: int, counts: np.ndarray, walls: np.ndarray, fill: bool,
) -> None:  # fmt: skip
    half_diag = cell * math.sqrt(0.5)
    for i in range(segments.shape[0]):
        ax = segments[i, 0]
        ay = segments[i, 1]
        bx = segments[i, 2]
        by = segments[i, 3]
        ca = min(max(int((min(ax, bx) - x0) // cell), 0), nx - 1)
        cb = min(max(int((max(ax, bx) - x0) // cell), 0), nx - 1)
        ra = min(max(int((min(ay, by) - y0) // cell), 0), ny - 1)
        rb = min(max(int((max(ay, by) - y0) // cell), 0), ny - 1)
        dx = bx - ax
        dy = by - ay
        length = math.hypot(dx, dy)
        for r in range(ra, rb + 1):
            cy = y0 + (r + 0.5) * cell
            for c in range(ca, cb + 1):
                cx = x0 + (c + 0.5) * cell
                if length > 0 and abs(dx * (cy - ay) - dy * (cx - ax)) / length > half_diag:
                    continue
                k = r * nx + c
                if fill:
                    walls[counts[k]] = i
                counts[k] += 1


@njit(cache=True, nogil=True)
def wall_cells(
    segments: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The wall index of :class:`rlutf.map.WallIndex`: ``(cell_start, cell_walls)``.

    A wall is listed in every cell of its bounding box whose centre lies within half a cell
    diagonal of the wall's supporting line (conservative: walls are short compared to a map, so
    the box is tight); each cell lists its walls in increasing order. Two passes: count, fill.
    """
    counts = np.zeros(nx * ny, dtype=np.int64)
    none = np.empty(0, dtype=np.int64)
    _visit_wall_cells(segments, x0, y0, cell, nx, ny, counts, none, False)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for k in range(nx * ny):
        start[k + 1] = start[k] + counts[k]
    walls = np.empty(start[nx * ny], dtype=np.int64)
    at = start[:-1].copy()
    _visit_wall_cells(segments, x0, y0, cell, nx, ny, at, walls, True)
    return start, walls
