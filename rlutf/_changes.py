"""Compiled kernels of map health (see :mod:`rlutf.mapchange`): a scan's evidence and its count."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def evidence(
    sx: float, sy: float, st: float, cos: np.ndarray, sin: np.ndarray, measured: np.ndarray,
    cast: np.ndarray, tolerance: float, nudge: float, ox: float, oy: float, cell: float,
    nx: int, ny: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``(short, through)`` flat cells of one scan from the sensor pose ``(sx, sy, st)``, each
    cell once, sorted (see :func:`rlutf.mapchange.scan_evidence`)."""
    n = measured.shape[0]
    cs, ss = math.cos(st), math.sin(st)
    short = np.empty(n, dtype=np.int64)
    through = np.empty(n, dtype=np.int64)
    ns = 0
    nt = 0
    for i in range(n):
        m, c = measured[i], cast[i]
        if not (math.isfinite(m) and math.isfinite(c)):
            continue
        if m < c - tolerance:
            at = m
        elif m > c + tolerance:
            at = c + nudge
        else:
            continue
        dx = cs * cos[i] - ss * sin[i]
        dy = ss * cos[i] + cs * sin[i]
        ix = int(math.floor((sx + at * dx - ox) / cell))
        iy = int(math.floor((sy + at * dy - oy) / cell))
        if ix < 0 or ix >= nx or iy < 0 or iy >= ny:
            continue
        if m < c:
            short[ns] = iy * nx + ix
            ns += 1
        else:
            through[nt] = iy * nx + ix
            nt += 1
    return np.unique(short[:ns]), np.unique(through[:nt])


@njit(cache=True, nogil=True)
def accumulate(
    marks: np.ndarray, windows: np.ndarray, robots: np.ndarray, first: np.ndarray,
    last: np.ndarray, cells: np.ndarray, stamp: int, window: np.uint32, robot: np.uint32,
) -> None:  # fmt: skip
    """Count one scan's cells of one kind (sums, ORs, min and max: any order, same result)."""
    for k in range(cells.shape[0]):
        c = cells[k]
        marks[c] += 1
        windows[c] |= window
        robots[c] |= robot
        first[c] = min(first[c], stamp)
        last[c] = max(last[c], stamp)
