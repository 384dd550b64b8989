"""A trial for maps built from logs: move the traced walls onto the hit points they stand for.

``rlutf map build`` traces the walls along the edges of the grid's free cells (moved into the
occupied cells by the built-map surface offset), so a wall at an angle to the grid runs in
steps about one cell high. The log holds the hit points of every scan at its corrected pose;
:func:`fit_walls` moves the traced rings' vertices so that the walls pass through them.

It is a regularised least-squares fit (an active contour): each hit is assigned to the nearest
wall within ``reach`` whose free side faces the scanner that saw it, and contributes its
distance to that wall along the wall's normal, the wall's end points moving with the hit's
position between them; every vertex is held to where it was (``stay``) and to its neighbours'
displacement along the ring (``smooth``), so that vertices without hits near them follow the
ones that have; a Huber weight (``huber``) keeps a person or a door from pulling a wall. The
assignment and the solve alternate ``iterations`` times; no vertex moves more than
``max_move``. The rings are then simplified again at ``simplify``.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import scipy.sparse as sp
import shapely
from scipy.sparse.linalg import spsolve
from shapely.geometry import MultiPolygon, Polygon

from bench.scenarios import FloatArray
from service.maps.mapimport.polygonize import polygonal


@dataclass(frozen=True)
class WallFit:
    """Settings of :func:`fit_walls` (lengths in metres).

    Attributes:
        reach: hits further than this from every wall are not used.
        stay: weight holding each vertex where it was (per square metre of displacement).
        smooth: weight holding a vertex's displacement to its neighbours' along the ring.
        huber: residuals over this are down-weighted (Huber).
        iterations: rounds of assignment and solve.
        max_move: no vertex moves further.
        simplify: Douglas-Peucker tolerance applied after the fit; 0 for none.
    """

    reach: float = 0.05
    stay: float = 0.05
    smooth: float = 0.2
    huber: float = 0.015
    iterations: int = 4
    max_move: float = 0.05
    simplify: float = 0.0125


def _rings(geometry: Polygon | MultiPolygon) -> tuple[list[Polygon], list[FloatArray]]:
    polys = [geometry] if isinstance(geometry, Polygon) else list(geometry.geoms)
    rings = [
        np.asarray(r.coords, dtype=np.float64)[:-1]
        for p in polys
        for r in (p.exterior, *p.interiors)
    ]
    return polys, rings


def fit_walls(
    geometry: Polygon | MultiPolygon, hits: FloatArray, sensors: FloatArray, fit: WallFit
) -> Polygon | MultiPolygon:
    """Move the rings' vertices onto the hit points.

    Args:
        geometry: the free space, valid polygons (map frame, metres).
        hits: ``(H, 2)`` hit points, metres.
        sensors: ``(H, 2)`` where the scanner stood for each hit, metres.
        fit: the settings.

    Returns:
        The free space with its walls moved, valid.
    """
    # Exteriors counter-clockwise, holes clockwise: the free side is on each edge's left.
    polys, rings = _rings(polygonal(shapely.orient_polygons(geometry)))
    starts = np.cumsum([0] + [len(r) for r in rings])
    head = np.arange(starts[-1])
    tail = np.concatenate([np.r_[np.arange(s + 1, e), s] for s, e in pairwise(starts)])
    origin = np.vstack(rings)
    n = len(origin)
    moved = np.zeros((n, 2))
    # Regularisation rows: stay where you were, move with your neighbour.
    hold = sp.identity(2 * n, format="csr") * np.sqrt(fit.stay)
    rows = np.repeat(np.arange(2 * n), 2)
    cols = np.column_stack([2 * head, 2 * tail, 2 * head + 1, 2 * tail + 1]).ravel()
    follow = sp.csr_matrix(
        (np.tile([1.0, -1.0], 2 * n) * np.sqrt(fit.smooth), (rows, cols)), shape=(2 * n, 2 * n)
    )
    points = shapely.points(hits)
    for _ in range(fit.iterations):
        now = origin + moved
        a, b = now[head], now[tail]
        tree = shapely.STRtree(shapely.linestrings(np.stack([a, b], axis=1)))
        hit, wall = tree.query_nearest(points, max_distance=fit.reach, all_matches=False)
        ab = b[wall] - a[wall]
        length = np.maximum(np.hypot(*ab.T), 1e-12)
        normal = np.column_stack([-ab[:, 1], ab[:, 0]]) / length[:, None]
        facing = ((sensors[hit] - a[wall]) * normal).sum(axis=1) > 0.0
        hit, wall, ab, length, normal = (
            hit[facing],
            wall[facing],
            ab[facing],
            length[facing],
            normal[facing],
        )
        t = np.clip(((hits[hit] - a[wall]) * ab).sum(axis=1) / length**2, 0.0, 1.0)
        on_wall = (1.0 - t)[:, None] * a[wall] + t[:, None] * b[wall]
        residual = ((on_wall - hits[hit]) * normal).sum(axis=1)
        weight = np.sqrt(np.minimum(1.0, fit.huber / np.maximum(np.abs(residual), 1e-12)))
        i, j = head[wall], tail[wall]
        coef = weight[:, None] * np.column_stack(
            [(1 - t) * normal[:, 0], (1 - t) * normal[:, 1], t * normal[:, 0], t * normal[:, 1]]
        )
        data = sp.csr_matrix(
            (
                coef.ravel(),
                (
                    np.repeat(np.arange(len(hit)), 4),
                    np.column_stack([2 * i, 2 * i + 1, 2 * j, 2 * j + 1]).ravel(),
                ),
            ),
            shape=(len(hit), 2 * n),
        )
        before = (1.0 - t)[:, None] * origin[i] + t[:, None] * origin[j]
        rhs = -weight * ((before - hits[hit]) * normal).sum(axis=1)
        system = sp.vstack([data, hold, follow]).tocsr()
        normal_eq = (system.T @ system).tocsc()
        solved = np.asarray(spsolve(normal_eq, data.T @ rhs)).reshape(n, 2)
        far = np.hypot(*solved.T)
        scale = np.minimum(1.0, fit.max_move / np.maximum(far, 1e-12))
        moved = solved * scale[:, None]
    now = origin + moved
    out: list[Polygon] = []
    k = 0
    for p in polys:
        count = 1 + len(p.interiors)
        parts = [now[starts[k + m] : starts[k + m + 1]] for m in range(count)]
        out.append(Polygon(parts[0], parts[1:]))
        k += count
    result = polygonal(out[0] if len(out) == 1 else MultiPolygon(out))
    if fit.simplify > 0.0:
        result = polygonal(shapely.simplify(result, fit.simplify, preserve_topology=True))
    return result
