"""Turning functions of polygons and the exact turning-function distance of Arkin et al.

The turning function of a closed polygon maps normalised arc length ``s`` in ``[0, 1)``,
measured counter-clockwise from the first vertex, to the direction angle (radians) of the edge
at ``s``. It is a step function that rises by each vertex's turning angle and by ``2*pi`` over a
full lap, so it extends to all ``s`` by ``f(s + 1) = f(s) + 2*pi``.

The distance is the paper's eq. 2.2 with ``p = 2`` (Arkin et al., 1991): the L2 distance of the
two turning functions, minimised over a rotation ``theta`` (a constant added to one function)
and over a start-point shift ``t`` in ``[0, 1)``. For a fixed ``t`` the best ``theta`` is the
mean difference of the functions, so ``d^2(t) = int (f - g)^2 - (int (f - g))^2``. Between two
*critical* shifts, where a breakpoint of one function meets a breakpoint of the other,
``int (f - g)^2`` is linear in ``t`` and ``int (f - g)`` is linear in ``t`` too, so ``d^2(t)`` is
concave there and its minimum lies at a critical shift. :func:`turning_match` evaluates
``d^2`` at all ``m * n`` critical shifts in one sorted sweep (``O(mn log mn)`` time, numpy
vectorised, memory bounded by processing the shifts in windows) and returns the exact minimum.

The metric is invariant under translation, rotation, uniform scaling, the choice of start
vertex and the orientation of the input ring. It is the shape-matching metric of the paper;
it is blind to where a polygon is, which pose tracking must get elsewhere.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.errors import GeometryError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

__all__ = ["TurningMatch", "turning_distance", "turning_function", "turning_match"]

_TWO_PI = 2.0 * math.pi
_FOUR_PI = 4.0 * math.pi
_FOUR_PI_SQ = 4.0 * math.pi * math.pi

# Edges shorter than this fraction of the ring's longest edge are zero-length: their direction
# is rounding noise and would add a spurious pair of turns.
_EDGE_TOL = 1e-9
# A turn within this many radians of +-pi is a fold-back: its sign is not determined by the
# geometry (rounding decides it), so it is chosen to make the ring's total turning 2*pi.
_FOLD_TOL = 1e-9
# Turns smaller than this (radians) join collinear consecutive edges into one piece.
_COLLINEAR_TOL = 1e-12
# Critical shifts swept per window; bounds memory to a few tens of MB for any polygon size.
_MAX_EVENTS = 1 << 18
# The shifts with the lowest swept d^2, up to _MAX_TIES of them and within _TIE_TOL of the
# minimum (the sweep's rounding is far below it), are re-evaluated directly.
_TIE_TOL = 1e-10
_MAX_TIES = 8
# Breakpoints this close (normalised arc length) are the same breakpoint moved by rounding.
_SNAP_TOL = 1e-12
# Slack (normalised arc length) when collecting a window's candidate shifts; every candidate is
# then assigned by its exact computed value, so this only has to exceed rounding error.
_WINDOW_MARGIN = 1e-9


class TurningMatch(NamedTuple):
    """The best alignment of two polygons under the turning-function metric.

    The alignment moves the first polygon ``a`` onto the second ``b``: rotate ``a`` by
    ``rotation`` radians counter-clockwise and start walking its boundary at normalised arc
    length ``shift`` (measured counter-clockwise from its first vertex, after orientation is
    normalised); its turning function then lies closest to that of ``b`` walked from ``b``'s
    first vertex, at L2 distance ``distance``. In formulas, with ``f`` and ``g`` the turning
    functions of ``a`` and ``b``::

        distance**2 == min over theta, t of  int_0^1 (f(s + t) + theta - g(s))**2 ds

    attained at ``theta == rotation`` (mod ``2*pi``) and ``t == shift``. If ``b`` is ``a``
    rotated counter-clockwise by ``phi`` (and possibly translated, scaled or re-started at
    another vertex), ``rotation`` is ``phi`` wrapped to ``[-pi, pi)``: the heading of ``b``
    minus the heading of ``a``. For a shape with rotational symmetry every symmetric
    alternative is equally good and one of them is returned.

    Attributes:
        distance: the turning-function distance, >= 0 (radians, since turning functions are
            angles over a unit-length domain).
        rotation: optimal rotation of ``a`` in radians, counter-clockwise, in ``[-pi, pi)``.
        shift: optimal start-point shift on ``a``, normalised arc length in ``[0, 1)``.
    """

    distance: float
    rotation: float
    shift: float


def turning_function(poly: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Compute the turning function of a closed polygon.

    The ring is cleaned first: a repeated closing vertex and other zero-length edges (shorter
    than 1e-9 times the longest edge) are dropped, the orientation is made counter-clockwise
    by signed area (keeping the first vertex as the start point), and consecutive collinear
    edges are merged. A 180-degree fold-back (an edge that doubles back on the previous one)
    turns by ``+pi`` or ``-pi``, whichever makes the total turning ``+2*pi``; where either
    would, the sign that cancels the turning of the neighbouring vertices is used (``+pi`` at
    the tip of an outward spike, ``-pi`` at the tip of an inward crack).

    Args:
        poly: vertices of a closed polygon, shape ``(N, 2)``, in any consistent length unit,
            either orientation, the closing vertex repeated or not.

    Returns:
        ``(s, angle)``, both shape ``(M,)`` float64 with ``M >= 2``: ``s`` holds the
        breakpoints, the normalised arc length in ``[0, 1)`` where each piece starts, strictly
        increasing with ``s[0] == 0``; ``angle[k]`` is the tangent direction in radians on
        ``[s[k], s[k + 1])`` (the last piece ends at 1). ``angle[0]`` is the direction of the
        first edge in ``[-pi, pi]``; later angles accumulate the turns, so they are not
        wrapped, and the function continues with ``angle[0] + 2*pi`` at ``s == 1``.

    Raises:
        GeometryError: if ``poly`` is not a finite ``(N, 2)`` array, has fewer than 3 distinct
            vertices or zero perimeter, or does not wind exactly once (a self-intersecting
            ring whose total turning cannot be made ``2*pi``).
    """
    edges, lengths = _clean_edges(poly)
    turns = _resolved_turns(edges)

    s = np.cumsum(lengths)
    s = np.concatenate(([0.0], s[:-1])) / s[-1]
    first = math.atan2(float(edges[0, 1]), float(edges[0, 0]))
    angle = np.cumsum(turns)
    angle += first - angle[0]

    keep = np.abs(turns) > _COLLINEAR_TOL
    keep[0] = True
    return s[keep], angle[keep]


def turning_distance(a: ArrayLike, b: ArrayLike) -> float:
    """Compute the exact turning-function distance between two polygons.

    This is the paper's eq. 2.2 with ``p = 2``: the L2 distance between the
    perimeter-normalised turning functions, minimised over rotation and start point. It is a
    metric on shapes up to translation, rotation and uniform scale (zero for similar
    polygons, symmetric, triangle inequality); see :func:`turning_match` for the minimiser.

    Args:
        a: first polygon, shape ``(N, 2)``; see :func:`turning_function` for what is accepted.
        b: second polygon, shape ``(M, 2)``.

    Returns:
        The distance, >= 0. For reference: unit square vs 2x1 rectangle ``pi*sqrt(5)/12``.

    Raises:
        GeometryError: if either polygon is invalid (see :func:`turning_function`).
    """
    return turning_match(a, b).distance


def turning_match(a: ArrayLike, b: ArrayLike) -> TurningMatch:
    """Find the rotation and start-point shift that best align ``a`` with ``b``.

    Runs in ``O(mn log mn)`` time for polygons of ``m`` and ``n`` vertices; two 100-vertex
    polygons take about a millisecond.

    Args:
        a: polygon that is rotated and re-started, shape ``(N, 2)``.
        b: reference polygon, shape ``(M, 2)``.

    Returns:
        The distance and the optimal rotation and shift of ``a`` relative to ``b``; see
        :class:`TurningMatch` for the exact convention.

    Raises:
        GeometryError: if either polygon is invalid (see :func:`turning_function`).
    """
    sa, fa = turning_function(a)
    sb, fb = turning_function(b)
    return _match_functions(sa, fa, sb, fb)


def _edges(ring: FloatArray) -> FloatArray:
    """Edge vectors of a ring: row ``i`` runs from vertex ``i`` to vertex ``i + 1``."""
    edges = np.empty_like(ring)
    np.subtract(ring[1:], ring[:-1], out=edges[:-1])
    np.subtract(ring[0], ring[-1], out=edges[-1])
    return edges


def _clean_edges(poly: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Validate a ring; return its edges, counter-clockwise, without zero-length ones.

    Returns:
        ``(edges, lengths)``: shape ``(M, 2)`` and ``(M,)``, where edge ``i`` runs from vertex
        ``i`` to vertex ``i + 1`` of the cleaned ring, which starts at the input's first vertex.
    """
    try:
        ring = np.asarray(poly, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise GeometryError(f"polygon must be an (N, 2) array of numbers: {err}") from err
    if ring.ndim != 2 or ring.shape[1] != 2:
        raise GeometryError(f"polygon must have shape (N, 2), got shape {ring.shape}")
    if ring.shape[0] < 3:
        raise GeometryError(f"polygon needs at least 3 distinct vertices, got {ring.shape[0]}")
    if not np.isfinite(ring).all():
        bad = int(np.flatnonzero(~np.isfinite(ring).all(axis=1))[0])
        raise GeometryError(f"polygon vertex {bad} is not finite: {ring[bad].tolist()}")

    edges = _edges(ring)
    lengths = np.hypot(edges[:, 0], edges[:, 1])
    longest = float(lengths.max())
    if longest == 0.0:
        raise GeometryError(
            f"polygon has zero perimeter: all {ring.shape[0]} vertices are {ring[0].tolist()}"
        )
    short = lengths <= _EDGE_TOL * longest
    while short.any():
        # Drop the vertex a short edge leads to, except that the start vertex stays: a short
        # closing edge drops the last vertex instead.
        drop = np.empty_like(short)
        drop[0] = False
        drop[1:] = short[:-1]
        drop[-1] |= short[-1]
        ring = ring[~drop]
        if ring.shape[0] < 3:
            break
        edges = _edges(ring)
        lengths = np.hypot(edges[:, 0], edges[:, 1])
        short = lengths <= _EDGE_TOL * longest

    x = ring[:, 0] - ring[0, 0]
    y = ring[:, 1] - ring[0, 1]
    twice_area = float(x[:-1] @ y[1:] - x[1:] @ y[:-1]) if ring.shape[0] >= 3 else 0.0
    if twice_area == 0.0:
        # Possibly fewer than 3 distinct vertices (A, B, A, B); check the first two's company.
        other = (ring != ring[0]).any(axis=1)
        if ring.shape[0] >= 3:
            other &= (ring != ring[int(np.argmax(other))]).any(axis=1)
        if ring.shape[0] < 3 or not other.any():
            distinct = min(ring.shape[0], 2)
            raise GeometryError(
                f"polygon needs at least 3 distinct vertices, got {distinct} after dropping "
                "zero-length edges"
            )
    if twice_area < 0.0:
        # Reverse to counter-clockwise from the same start vertex: edges reverse and flip.
        edges = -edges[::-1]
        lengths = lengths[::-1]
    return edges, lengths


def _resolved_turns(edges: FloatArray) -> FloatArray:
    """Turning angle at each vertex, fold-backs resolved so that the total is ``2*pi``.

    ``turns[i]`` is the turn at vertex ``i``, from ``edges[i - 1]`` to ``edges[i]``.
    """
    prev = np.concatenate((edges[-1:], edges[:-1]))
    cross = prev[:, 0] * edges[:, 1] - prev[:, 1] * edges[:, 0]
    dot = prev[:, 0] * edges[:, 0] + prev[:, 1] * edges[:, 1]
    turns = np.arctan2(cross, dot)

    fold = np.abs(turns) > math.pi - _FOLD_TOL
    if fold.any():
        # Left-turn version of each fold-back (about +pi), and the pull of its neighbours: a
        # spike tip cancels the turns at the spike's base, so a right-turning base (outward
        # spike) wants +pi and a left-turning base (inward crack) wants -pi.
        left = np.where(turns > 0.0, turns, turns + _TWO_PI)
        plain = np.where(fold, 0.0, turns)
        pull = np.roll(plain, 1) + np.roll(plain, -1)
        turns = np.where(fold, np.where(pull > _FOLD_TOL, left - _TWO_PI, left), turns)

        winding = round(float(turns.sum()) / _TWO_PI)
        if winding != 1:
            # Flip the fold-backs whose neighbours care least until the ring winds once.
            wrong_sign = fold & ((turns > 0.0) if winding > 1 else (turns < 0.0))
            idx = np.flatnonzero(wrong_sign)
            order = idx[np.argsort(np.abs(pull[idx]), kind="stable")]
            flip = order[: abs(winding - 1)]
            turns[flip] -= math.copysign(_TWO_PI, winding - 1)

    total = float(turns.sum())
    if round(total / _TWO_PI) != 1:
        raise GeometryError(
            f"polygon does not wind exactly once: its total turning is {total:.6g} rad, "
            "not 2*pi (a self-intersecting ring)"
        )
    return turns


def _piece_widths(s: FloatArray) -> FloatArray:
    """Lengths of the pieces that start at the breakpoints ``s`` (the last one ends at 1)."""
    width = np.empty_like(s)
    np.subtract(s[1:], s[:-1], out=width[:-1])
    width[-1] = 1.0 - s[-1]
    return width


def _shift_cost(
    sa: FloatArray, fa: FloatArray, sb: FloatArray, fb: FloatArray, t: float
) -> tuple[float, float]:
    """Evaluate one shift directly: ``d^2(t)`` and the mean of ``f(s + t) - g(s)``.

    Independent of the sweep and free of its cumulative rounding, so it gives the final
    distance and rotation at the chosen shift.
    """
    shifted = sa - t
    shifted += shifted < 0.0
    # A breakpoint of f that rounding put next to one of g's leaves a sliver of width ~1e-16
    # that adds ~1e-16 to d^2, i.e. ~1e-8 to a zero distance: snap it onto g's.
    ref = np.append(sb, 1.0)
    k = np.searchsorted(ref, shifted)
    k[k == 0] = 1  # only shifted == 0 == ref[0]
    below, above = ref[k - 1], ref[k]
    shifted = np.where(
        shifted - below <= _SNAP_TOL, below, np.where(above - shifted <= _SNAP_TOL, above, shifted)
    )
    cuts = np.sort(np.concatenate(([0.0], shifted, sb)))
    width = _piece_widths(cuts)
    mid = cuts + 0.5 * width
    x = mid + t
    wrapped = x >= 1.0
    x = np.where(wrapped, x - 1.0, x)
    fv = fa[np.searchsorted(sa, x, side="right") - 1] + _TWO_PI * wrapped
    gv = fb[np.searchsorted(sb, mid, side="right") - 1]
    diff = fv - gv
    mean = float(width @ diff)
    return float(width @ (diff - mean) ** 2), mean


def _argsort_unit(t: FloatArray) -> IntArray:
    """Indices that sort ``t``, values in ``[0, 1]``; faster than ``np.argsort``.

    Sorts int64 keys that hold ``t`` in fixed point above the index (a plain sort is several
    times faster than an indirect one). Values closer than ``2**-(62 - index bits)`` (below
    1e-13 for up to 2**18 values) may come out in index order; the sweep's error from such a
    swap is the slope change times that gap.
    """
    n = t.shape[0]
    bits = max(1, (n - 1).bit_length())
    key = (t * float(1 << (62 - bits))).astype(np.int64)
    key <<= bits
    key |= np.arange(n, dtype=np.int64)
    key.sort()
    key &= (1 << bits) - 1
    return key.astype(np.intp, copy=False)


def _window_pairs(
    sa: FloatArray, sb: FloatArray, lo: float, hi: float
) -> tuple[IntArray, IntArray]:
    """Index pairs ``(i, j)`` whose shift ``(sa[i] - sb[j]) % 1`` may lie in ``[lo, hi)``.

    A superset by ``_WINDOW_MARGIN``; the caller filters on the computed shifts.
    """
    m, n = sa.shape[0], sb.shape[0]
    # sa[i] - sb[j] = t (mod 1)  <=>  sa[i] + k = sb[j] + t for some integer k in {-1, 0, 1}.
    a_ext = np.concatenate((sa - 1.0, sa, sa + 1.0))
    start = np.searchsorted(a_ext, sb + (lo - _WINDOW_MARGIN))
    stop = np.searchsorted(a_ext, sb + (min(hi, 1.0) + _WINDOW_MARGIN))
    count = np.minimum(stop - start, m)
    jj = np.repeat(np.arange(n), count)
    offset = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    ii = (np.repeat(start, count) + offset) % m
    return ii.astype(np.intp), jj.astype(np.intp)


def _match_functions(
    sa: FloatArray,
    fa: FloatArray,
    sb: FloatArray,
    fb: FloatArray,
    max_events: int = _MAX_EVENTS,
) -> TurningMatch:
    """Exact minimum of ``d^2(t)`` over all critical shifts, for two turning functions.

    With both functions centred (mean zero; the rotation absorbs constants) and ``f`` extended
    by ``f(s + 1) = f(s) + 2*pi``, ``int_0^1 f(s + t) ds = 2*pi*t`` and
    ``int_0^1 f(s + t)^2 ds = F2 + 4*pi*F1(t) + 4*pi^2*t``, so::

        d^2(t) = F2 + G2 + 4*pi^2*t*(1 - t) + Y(t),    Y(t) = 4*pi*F1(t) - 2*X(t)

    where ``F2 = int f^2``, ``G2 = int g^2``, ``F1(t) = int_0^t f`` and
    ``X(t) = int_0^1 f(s + t) g(s) ds``. ``Y`` is continuous and piecewise linear: the slope of
    ``X`` is ``sum_i jump_f[i] * g((sa[i] - t) mod 1)``, which changes by
    ``-jump_f[i] * jump_g[j]`` at the critical shift ``(sa[i] - sb[j]) mod 1``, and the slope of
    ``F1`` is ``f(t)``, which changes by ``jump_f[i]`` at ``sa[i]`` (the shifts with ``j = 0``).
    So ``d^2`` is concave between critical shifts, and sweeping them in sorted order while
    accumulating the slope and ``Y`` gives ``d^2`` at all of them. The sweep starts at shift 0
    with ``Y`` and its slope (just before 0) evaluated directly, and runs in windows of at most
    about ``max_events`` shifts to bound memory.
    """
    m, n = sa.shape[0], sb.shape[0]
    wa, wb = _piece_widths(sa), _piece_widths(sb)
    f = fa - float(wa @ fa)
    g = fb - float(wb @ fb)
    jump_f = np.empty_like(f)
    np.subtract(f[1:], f[:-1], out=jump_f[1:])
    jump_f[0] = f[0] + _TWO_PI - f[-1]
    # Twice the jumps of g restricted to [0, 1) (so no 2*pi at s = 0), plus F1's 4*pi at j = 0.
    weight_g = np.empty_like(g)
    np.subtract(g[1:], g[:-1], out=weight_g[1:])
    weight_g[0] = g[0] - g[-1]
    weight_g *= 2.0
    weight_g[0] += _FOUR_PI

    cuts = np.sort(np.concatenate((sa, sb)))
    x0 = float(
        _piece_widths(cuts)
        @ (
            f[np.searchsorted(sa, cuts, side="right") - 1]
            * g[np.searchsorted(sb, cuts, side="right") - 1]
        )
    )
    # The slope of Y just before t = 0, so that the sweep applies the shifts of exactly 0 too:
    # X's uses g at each sa[i] itself, F1's is f(0-) = f(1-) - 2*pi.
    slope_x = float(jump_f @ g[np.searchsorted(sb, sa, side="right") - 1])
    slope = _FOUR_PI * (float(f[-1]) - _TWO_PI) - 2.0 * slope_x
    t_prev, y_prev = 0.0, -2.0 * x0
    # Per window, the shifts whose d^2 is near that window's minimum, as (d^2 - F2 - G2, t).
    near_d2: list[FloatArray] = [np.array([y_prev])]
    near_t: list[FloatArray] = [np.array([0.0])]

    windows = max(1, -(-(m * n) // max_events))
    for w in range(windows):
        if windows == 1:
            t = np.subtract.outer(sb, sa).ravel()
            np.negative(t, out=t)
            t += t < 0.0  # (sa[i] - sb[j]) mod 1
            change = np.multiply.outer(weight_g, jump_f).ravel()
        else:
            lo = w / windows
            hi = math.inf if w == windows - 1 else (w + 1) / windows
            ii, jj = _window_pairs(sa, sb, lo, hi)
            t = sa[ii] - sb[jj]
            t += t < 0.0  # computed exactly as above, so each shift lands in one window
            keep = (t >= lo) & (t < hi)
            t = t[keep]
            change = weight_g[jj[keep]] * jump_f[ii[keep]]
            if t.shape[0] == 0:
                continue
        order = _argsort_unit(t)
        t, change = t[order], change[order]
        slope_after = np.cumsum(change)
        slope_after += slope
        # y[k] = y_prev + sum over l <= k of (slope before shift l) * (t[l] - t[l - 1]).
        y = np.empty_like(t)
        y[0] = slope * (t[0] - t_prev)
        np.subtract(t[1:], t[:-1], out=y[1:])
        y[1:] *= slope_after[:-1]
        np.cumsum(y, out=y)
        y += y_prev
        d2 = _FOUR_PI_SQ * t * (1.0 - t)
        d2 += y
        near = d2 <= float(d2.min()) + _TIE_TOL
        near_d2.append(d2[near])
        near_t.append(t[near])
        t_prev, y_prev, slope = float(t[-1]), float(y[-1]), float(slope_after[-1])

    cand_d2 = np.concatenate(near_d2)
    cand_t = np.concatenate(near_t)
    lowest = np.argsort(cand_d2)[:_MAX_TIES]
    lowest = lowest[cand_d2[lowest] <= float(cand_d2.min()) + _TIE_TOL]
    # Smallest shifts first, so an exact tie resolves to the smallest shift.
    cand_t = np.sort(cand_t[lowest] % 1.0)
    best_d2, best_mean, best_t = math.inf, 0.0, 0.0
    for t_cand in cand_t.tolist():
        d2_direct, mean_diff = _shift_cost(sa, fa, sb, fb, t_cand)
        if d2_direct < best_d2:
            best_d2, best_mean, best_t = d2_direct, mean_diff, t_cand
    rotation = (-best_mean + math.pi) % _TWO_PI - math.pi
    if rotation >= math.pi:  # rounding of an angle just under pi
        rotation -= _TWO_PI
    return TurningMatch(distance=math.sqrt(max(best_d2, 0.0)), rotation=rotation, shift=best_t)
