"""Compiled branch and bound over a multi-resolution grid (see :mod:`rlutf.relocalize`).

Level ``k`` of a pyramid holds, at cell ``(row, col)``, the maximum of the base grid over the
``2^k`` by ``2^k`` window that starts there (Cartographer's FastCorrelativeScanMatcher2D), so the
sum of a scan's points looked up at level ``k`` bounds from above the score of every translation
of the node's window: pruning on it is exact.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pyramid(base: np.ndarray, depth: int) -> np.ndarray:
    """``(depth, H, W)``: level ``k`` is the maximum of ``base`` over ``2^k``-wide windows."""
    height, width = base.shape
    out = np.zeros((depth, height, width), dtype=base.dtype)
    out[0] = base
    for k in range(1, depth):
        s = 1 << (k - 1)
        prev = out[k - 1]
        cur = out[k]
        for y in range(height):
            for x in range(width):
                m = prev[y, x]
                if x + s < width and prev[y, x + s] > m:
                    m = prev[y, x + s]
                if y + s < height:
                    m = max(m, prev[y + s, x])
                    if x + s < width and prev[y + s, x + s] > m:
                        m = prev[y + s, x + s]
                cur[y, x] = m
    return out


@njit(cache=True, nogil=True)
def _bound(
    level: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    i: int,
    j: int,
    span: int,
    extent: np.ndarray,
) -> int:
    """Sum over the points of the level's value at their window ``[col, col + span)``. A window
    that starts left of or below the grid but reaches into it is read at the grid's edge: that
    window's maximum covers the part inside, so the bound stays an upper bound. ``extent``:
    the points' smallest and largest column and row offsets, ``(min cx, max cx, min cy, max
    cy)``: a node whose every point falls inside the grid (most, on a large map) is summed
    without the edge checks."""
    height, width = level.shape
    total = 0
    if (
        i + extent[0] >= 0
        and i + extent[1] < width
        and j + extent[2] >= 0
        and j + extent[3] < height
    ):
        for p in range(len(cx)):  # every point inside the grid: no edge to mind
            total += level[j + cy[p], i + cx[p]]
        return total
    for p in range(len(cx)):
        col = i + cx[p]
        row = j + cy[p]
        if col < 0 < col + span:
            col = 0
        if row < 0 < row + span:
            row = 0
        if 0 <= col < width and 0 <= row < height:
            total += level[row, col]
    return total


@njit(cache=True, nogil=True)
def _in_region(i: int, j: int, span: int, region: np.ndarray) -> bool:
    """Whether the window of cells ``[i, i + span) x [j, j + span)`` meets the circle
    ``region = (col, row, radius)`` (cells; radius < 0: no region)."""
    if region[2] < 0.0:
        return True
    dx = max(i - region[0], 0.0, region[0] - (i + span - 1))
    dy = max(j - region[1], 0.0, region[1] - (j + span - 1))
    return bool(dx * dx + dy * dy <= region[2] * region[2])


@njit(cache=True, nogil=True)
def _by_bound(bounds: np.ndarray, count: int) -> np.ndarray:
    """The indices of ``bounds[:count]`` (non-negative) from the highest bound down, equal
    bounds in index order: a counting sort, the order a stable sort of the negated bounds gives,
    in 4 bytes an index and no copy of the bounds (``count`` < 2^31: that many top nodes would
    take 25 GB)."""
    top = 0
    for t in range(count):
        top = max(top, bounds[t])
    start = np.zeros(top + 2, dtype=np.int64)
    for t in range(count):
        start[top - bounds[t] + 1] += 1
    for v in range(1, top + 2):
        start[v] += start[v - 1]
    order = np.empty(count, dtype=np.int32)
    for t in range(count):
        slot = top - bounds[t]
        order[start[slot]] = t
        start[slot] += 1
    return order


@njit(cache=True, nogil=True)
def search(
    levels: np.ndarray,
    valid: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    region: np.ndarray,
    min_total: int,
    keep: int,
    apart_cells: int,
    apart_turns: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The ``keep`` best distinct translations and rotations of a scan, exactly.

    Args:
        levels: ``(D, H, W)`` uint8 score pyramid.
        valid: ``(D, H, W)`` uint8 pyramid of the cells where the robot may stand.
        cx: ``(R, n)`` int column offsets of the scan's points for each rotation.
        cy: ``(R, n)`` the same for rows.
        region: ``(col, row, radius)`` in cells; a negative radius for the whole map.
        min_total: leaves scoring under this sum are not kept.
        keep: how many distinct poses to return.
        apart_cells: poses closer than this in both columns and rows ...
        apart_turns: ... and this in rotation steps are the same pose (the better kept).

    Returns:
        ``(totals, rotations, cols, rows, nodes scored)``, best first, ``keep`` long; entries
        past the found ones have total -1.
    """
    depth, height, width = levels.shape
    turns = cx.shape[0]
    top = depth - 1
    stride = 1 << top
    n_cols = (width + stride - 1) // stride
    n_rows = (height + stride - 1) // stride
    # Every top node of every rotation, bounded: each kept as its index in (rotation, column,
    # row) order and its bound, 12 bytes (a large site's map has millions of them).
    extents = np.empty((turns, 4), dtype=np.int64)
    for r in range(turns):
        extents[r, 0] = cx[r].min()
        extents[r, 1] = cx[r].max()
        extents[r, 2] = cy[r].min()
        extents[r, 3] = cy[r].max()
    count = 0
    per_turn = n_cols * n_rows
    nodes = np.empty(turns * per_turn, dtype=np.int64)
    bounds = np.empty(turns * per_turn, dtype=np.int32)
    scored = 0
    for r in range(turns):
        for a in range(n_cols):
            for b in range(n_rows):
                i, j = a * stride, b * stride
                if valid[top, j, i] == 0 or not _in_region(i, j, stride, region):
                    continue
                bounds[count] = _bound(levels[top], cx[r], cy[r], i, j, stride, extents[r])
                nodes[count] = r * per_turn + a * n_rows + b
                count += 1
    scored += count
    order = _by_bound(bounds, count)
    totals = np.full(keep, -1, dtype=np.int64)
    rots = np.zeros(keep, dtype=np.int64)
    cols = np.zeros(keep, dtype=np.int64)
    rows = np.zeros(keep, dtype=np.int64)
    found = 0
    threshold = min_total - 1
    # Depth-first below each top node, best child first.
    stack = np.empty((4 * depth + 4, 5), dtype=np.int64)
    child = np.empty((4, 5), dtype=np.int64)
    for t in range(count):
        node = order[t]
        if bounds[node] <= threshold:
            break
        sp = 0
        index = nodes[node]
        stack[0, 0] = top
        stack[0, 1] = index // per_turn
        stack[0, 2] = (index % per_turn) // n_rows * stride
        stack[0, 3] = index % n_rows * stride
        stack[0, 4] = bounds[node]
        sp = 1
        while sp > 0:
            sp -= 1
            k, r, i, j, b = stack[sp, 0], stack[sp, 1], stack[sp, 2], stack[sp, 3], stack[sp, 4]
            if b <= threshold:
                continue
            if k == 0:
                if valid[0, j, i] == 0 or not _in_region(i, j, 1, region):
                    continue
                # A leaf's bound is its score. Same pose as a kept one: keep the better.
                same = -1
                for q in range(found):
                    dr = abs(rots[q] - r)
                    dr = min(dr, turns - dr)
                    if (
                        abs(cols[q] - i) < apart_cells
                        and abs(rows[q] - j) < apart_cells
                        and dr < apart_turns
                    ):
                        same = q
                        break
                if same >= 0:
                    if b <= totals[same]:
                        continue
                    for q in range(same, found - 1):
                        totals[q] = totals[q + 1]
                        rots[q] = rots[q + 1]
                        cols[q] = cols[q + 1]
                        rows[q] = rows[q + 1]
                    found -= 1
                # Insert in order.
                at = found
                while at > 0 and totals[at - 1] < b:
                    at -= 1
                if at >= keep:
                    continue
                last = min(found, keep - 1)
                for q in range(last, at, -1):
                    totals[q] = totals[q - 1]
                    rots[q] = rots[q - 1]
                    cols[q] = cols[q - 1]
                    rows[q] = rows[q - 1]
                totals[at] = b
                rots[at] = r
                cols[at] = i
                rows[at] = j
                found = min(found + 1, keep)
                if found == keep:
                    threshold = max(threshold, totals[keep - 1])
                continue
            s = 1 << (k - 1)
            m = 0
            for d in range(4):
                ci = i + (s if d & 1 else 0)
                cj = j + (s if d & 2 else 0)
                if ci >= width or cj >= height or valid[k - 1, cj, ci] == 0:
                    continue
                if not _in_region(ci, cj, s, region):
                    continue
                cb = _bound(levels[k - 1], cx[r], cy[r], ci, cj, s, extents[r])
                scored += 1
                if cb <= threshold:
                    continue
                child[m, 0] = k - 1
                child[m, 1] = r
                child[m, 2] = ci
                child[m, 3] = cj
                child[m, 4] = cb
                m += 1
            # Sort the children by bound (insertion sort of at most four) and push the worst
            # first, so that the best is explored first.
            for q in range(1, m):
                for z in range(q, 0, -1):
                    if child[z, 4] < child[z - 1, 4]:
                        for c in range(5):
                            tmp = child[z, c]
                            child[z, c] = child[z - 1, c]
                            child[z - 1, c] = tmp
            for q in range(m):
                stack[sp] = child[q]
                sp += 1
    return totals, rots, cols, rows, scored
