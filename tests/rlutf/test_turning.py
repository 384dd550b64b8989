"""Tests of :mod:`rlutf.turning`: reference values, metric properties, brute force, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from rlutf.errors import GeometryError
from rlutf.turning import (
    TurningMatch,
    _match_functions,
    turning_distance,
    turning_function,
    turning_match,
)

FloatArray = NDArray[np.float64]

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
RECTANGLE = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])
TRIANGLE = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, math.sqrt(3.0) / 2.0]])
HEXAGON = np.array([[math.cos(k * math.pi / 3), math.sin(k * math.pi / 3)] for k in range(6)])
# No rotational or mirror symmetry, so its best alignment with a rotated copy is unique.
LOPSIDED = np.array([[0.0, 0.0], [4.0, 0.0], [4.5, 1.0], [2.0, 2.5], [1.0, 1.2], [-0.5, 1.0]])
# Unit square with a zero-width spike: outward (down from the bottom edge) and inward (up).
OUTWARD_SPIKE = np.array(
    [[0.0, 0.0], [0.5, 0.0], [0.5, -1.0], [0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
)
INWARD_SPIKE = np.array(
    [[0.0, 0.0], [0.5, 0.0], [0.5, 0.5], [0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
)

TIGHT = 1e-9  # for quantities that are equal up to rounding
# Near zero, d = sqrt(d^2) turns rounding of the input coordinates (relative 1e-16 times the
# ratio of coordinate magnitude to polygon size, up to 1e4 here) into errors up to ~1e-6.
NEAR_ZERO = 1e-6


def rotate(poly: FloatArray, phi: float) -> FloatArray:
    """Rotate a polygon counter-clockwise by ``phi`` radians about the origin."""
    c, s = math.cos(phi), math.sin(phi)
    return np.asarray(poly @ np.array([[c, s], [-s, c]]), dtype=np.float64)


def angle_gap(x: float, y: float) -> float:
    """Absolute difference of two angles, modulo 2*pi."""
    return abs((x - y + math.pi) % (2.0 * math.pi) - math.pi)


@st.composite
def star_polygons(draw: st.DrawFn, min_vertices: int = 3, max_vertices: int = 12) -> FloatArray:
    """Simple polygons: vertices at random radii around the origin, in angular order.

    Every angular gap is below pi (gaps are drawn from [1, 1.9] and normalised), so the origin
    sees the whole boundary and the polygon is simple.
    """
    n = draw(st.integers(min_vertices, max_vertices))
    gaps = np.array(draw(st.lists(st.floats(1.0, 1.9), min_size=n, max_size=n)))
    radii = np.array(draw(st.lists(st.floats(0.2, 1.0), min_size=n, max_size=n)))
    start = draw(st.floats(0.0, 2.0 * math.pi))
    angles = start + 2.0 * math.pi * np.cumsum(gaps) / gaps.sum()
    return np.column_stack((radii * np.cos(angles), radii * np.sin(angles)))


def brute_force_distance(a: FloatArray, b: FloatArray, samples: int = 1 << 16) -> float:
    """Sampled reference: both turning functions on a fine s grid, every grid shift t.

    For each shift ``t = k / samples`` the rotation is the closed-form optimum (the mean
    difference), so ``d^2(t)`` is the variance of ``f(s + t) - g(s)`` over the grid, with
    ``f(s + 1) = f(s) + 2*pi``. All shifts at once by FFT cross-correlation.
    """
    sa, fa = turning_function(a)
    sb, fb = turning_function(b)
    s = (np.arange(samples) + 0.5) / samples
    f = fa[np.searchsorted(sa, s, side="right") - 1]
    g = fb[np.searchsorted(sb, s, side="right") - 1]
    k = np.arange(samples)
    # sum_j f_ext[j + k] * g[j], where f_ext[i] = f[i - samples] + 2*pi beyond the end.
    corr = np.fft.irfft(np.fft.rfft(f) * np.conj(np.fft.rfft(g)), samples)
    g_tail = np.concatenate(([0.0], np.cumsum(g[::-1])))[k]
    cross = corr + 2.0 * math.pi * g_tail
    f_head = np.concatenate(([0.0], np.cumsum(f)))[k]
    sum_sq = f @ f + 4.0 * math.pi * f_head + 4.0 * math.pi**2 * k
    mean = (f.sum() + 2.0 * math.pi * k - g.sum()) / samples
    d2 = (sum_sq - 2.0 * cross + g @ g) / samples - mean**2
    return math.sqrt(max(float(d2.min()), 0.0))


# --- turning_function -------------------------------------------------------------------


def test_square_turning_function() -> None:
    s, angle = turning_function(SQUARE)
    np.testing.assert_allclose(s, [0.0, 0.25, 0.5, 0.75])
    np.testing.assert_allclose(angle, [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])
    assert s.dtype == np.float64
    assert angle.dtype == np.float64


def test_clockwise_ring_is_reoriented_from_the_same_start_vertex() -> None:
    clockwise = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]])
    s, angle = turning_function(clockwise)
    np.testing.assert_allclose(s, [0.0, 0.25, 0.5, 0.75])
    np.testing.assert_allclose(angle, [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])


def test_closing_vertex_zero_length_edges_and_collinear_vertices_are_dropped() -> None:
    messy = [
        [0.0, 0.0],
        [0.0, 0.0],
        [0.5, 0.0],
        [1.0, 0.0],
        [1.0, 0.0],
        [1.0, 1.0],
        [0.0, 1.0],
        [0.0, 1.0],
        [0.0, 0.0],
    ]
    s, angle = turning_function(messy)
    np.testing.assert_allclose(s, [0.0, 0.25, 0.5, 0.75])
    np.testing.assert_allclose(angle, [0.0, math.pi / 2, math.pi, 3 * math.pi / 2])
    assert turning_distance(messy, SQUARE) < TIGHT


@pytest.mark.parametrize(
    ("poly", "base_turn", "tip_turn"),
    [(OUTWARD_SPIKE, -math.pi / 2, math.pi), (INWARD_SPIKE, math.pi / 2, -math.pi)],
)
def test_fold_back_turns_by_the_sign_that_closes_the_spike(
    poly: FloatArray, base_turn: float, tip_turn: float
) -> None:
    _, angle = turning_function(poly)
    quarter = math.pi / 2
    # Turns at vertices 1..6: spike base, tip, base, then the square's corners.
    expected = [base_turn, tip_turn, base_turn, quarter, quarter, quarter]
    np.testing.assert_allclose(np.diff(angle), expected, atol=1e-12)
    closing = angle[0] + 2.0 * math.pi - angle[-1]  # the turn at vertex 0
    assert closing == pytest.approx(quarter)


@given(phi=st.floats(-math.pi, math.pi), start=st.integers(0, 6))
@settings(max_examples=40, deadline=None)
def test_fold_backs_survive_rotation_reversal_and_restart(phi: float, start: int) -> None:
    # Rotation turns the exact fold-backs into near ones whose atan2 sign is rounding noise.
    for poly in (OUTWARD_SPIKE, INWARD_SPIKE):
        moved = np.roll(rotate(poly, phi), start, axis=0)
        assert turning_distance(poly, moved) < NEAR_ZERO
        assert turning_distance(poly, moved[::-1]) < NEAR_ZERO
    assert turning_distance(OUTWARD_SPIKE, INWARD_SPIKE) > 0.1


@given(a=star_polygons(max_vertices=30), scale=st.floats(0.01, 100.0))
@settings(max_examples=50, deadline=None)
def test_turning_function_shape_and_similarity_invariance(a: FloatArray, scale: float) -> None:
    s, angle = turning_function(a)
    assert s.shape == angle.shape
    assert s[0] == 0.0
    assert np.all(np.diff(s) > 0.0)
    assert s[-1] < 1.0
    first = a[1] - a[0]
    assert angle[0] == pytest.approx(math.atan2(first[1], first[0]))
    # A simple polygon has no fold-backs: every turn, the closing one too, is within (-pi, pi).
    assert np.all(np.abs(np.diff(angle)) < math.pi)
    closing = angle[0] + 2.0 * math.pi - angle[-1]
    assert -math.pi < closing < math.pi
    s2, angle2 = turning_function(scale * a + np.array([3.0, -2.0]))
    np.testing.assert_allclose(s2, s, atol=1e-12)
    np.testing.assert_allclose(angle2, angle, atol=1e-9)


def test_degenerate_collinear_ring_folds_back_twice() -> None:
    s, angle = turning_function([[0.0, 0.0], [2.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(s, [0.0, 0.5])
    np.testing.assert_allclose(angle, [0.0, math.pi])


@pytest.mark.parametrize(
    ("poly", "message"),
    [
        ([], "shape"),
        ([0.0, 1.0, 2.0, 3.0], "shape"),
        ([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "shape"),
        (np.zeros((3, 2, 1)), "shape"),
        ([[0.0, 0.0], [1.0]], "array of numbers"),
        ("square", "array of numbers"),
        ([[0.0, 0.0], [1.0, 1.0]], "at least 3 distinct"),
        ([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0], [0.0, 0.0]], "at least 3 distinct"),
        ([[0.0, 0.0], [1.0, 1.0], [0.0, 0.0], [1.0, 1.0]], "at least 3 distinct"),
        ([[2.0, 3.0]] * 4, "zero perimeter"),
        ([[0.0, 0.0], [1.0, 0.0], [math.nan, 1.0]], "vertex 2 is not finite"),
        ([[0.0, 0.0], [math.inf, 0.0], [0.0, 1.0]], "vertex 1 is not finite"),
        ([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]], "wind exactly once"),
    ],
)
def test_invalid_polygons_raise_geometry_error(poly: object, message: str) -> None:
    with pytest.raises(GeometryError, match=message):
        turning_function(poly)  # type: ignore[arg-type]
    with pytest.raises(GeometryError, match=message):
        turning_distance(SQUARE, poly)  # type: ignore[arg-type]


# --- reference values -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        (SQUARE, SQUARE, 0.0),
        (SQUARE, RECTANGLE, math.pi * math.sqrt(5.0) / 12.0),
        (SQUARE, TRIANGLE, 0.724890),
        (SQUARE, HEXAGON, 0.501308),
    ],
)
def test_reference_distances(a: FloatArray, b: FloatArray, expected: float) -> None:
    assert turning_distance(a, b) == pytest.approx(expected, abs=1e-5)
    assert turning_distance(b, a) == pytest.approx(expected, abs=1e-5)


def test_match_of_identical_polygons_is_the_identity() -> None:
    assert turning_match(SQUARE, SQUARE) == TurningMatch(distance=0.0, rotation=0.0, shift=0.0)


# --- rotation and shift of the match --------------------------------------------------------


@given(
    phi=st.floats(-math.pi, math.pi, exclude_max=True),
    start=st.integers(0, LOPSIDED.shape[0] - 1),
    scale=st.floats(0.01, 100.0),
    offset=st.tuples(st.floats(-50.0, 50.0), st.floats(-50.0, 50.0)),
)
@settings(max_examples=60, deadline=None)
def test_rotation_recovers_the_heading_of_a_rotated_copy(
    phi: float, start: int, scale: float, offset: tuple[float, float]
) -> None:
    moved = scale * rotate(np.roll(LOPSIDED, -start, axis=0), phi) + np.array(offset)
    match = turning_match(LOPSIDED, moved)
    assert match.distance < NEAR_ZERO
    assert angle_gap(match.rotation, phi) < NEAR_ZERO
    assert -math.pi <= match.rotation < math.pi
    # moved starts at LOPSIDED's vertex `start`, which is this far along LOPSIDED's boundary.
    s, _ = turning_function(LOPSIDED)
    assert angle_gap(2 * math.pi * match.shift, 2 * math.pi * s[start]) < NEAR_ZERO
    assert 0.0 <= match.shift < 1.0
    back = turning_match(moved, LOPSIDED)
    assert angle_gap(back.rotation, -phi) < NEAR_ZERO


@given(a=star_polygons(), b=star_polygons())
@settings(max_examples=40, deadline=None)
def test_rotation_and_shift_attain_the_distance(a: FloatArray, b: FloatArray) -> None:
    match = turning_match(a, b)
    sa, fa = turning_function(a)
    sb, fb = turning_function(b)
    s = (np.arange(1 << 18) + 0.5) / (1 << 18)
    u = s + match.shift
    laps = np.floor(u)
    f = fa[np.searchsorted(sa, u - laps, side="right") - 1] + 2.0 * math.pi * laps
    g = fb[np.searchsorted(sb, s, side="right") - 1]
    diff = f - g
    # The best theta for this shift is -mean(diff); it is the reported rotation mod 2*pi.
    assert angle_gap(-float(diff.mean()), match.rotation) < 1e-3
    # Sampling misplaces each breakpoint by up to 2**-19, so compare d^2 (error ~1e-5 each).
    assert float(diff.var()) == pytest.approx(match.distance**2, abs=1e-3)


# --- metric properties ----------------------------------------------------------------------


@given(a=star_polygons(max_vertices=30))
@settings(max_examples=50, deadline=None)
def test_distance_to_itself_is_zero(a: FloatArray) -> None:
    assert turning_distance(a, a) < TIGHT


@given(a=star_polygons(), b=star_polygons())
@settings(max_examples=50, deadline=None)
def test_symmetry(a: FloatArray, b: FloatArray) -> None:
    assert turning_distance(a, b) == pytest.approx(turning_distance(b, a), abs=TIGHT)


@given(
    a=star_polygons(),
    b=star_polygons(),
    phi=st.floats(-math.pi, math.pi),
    scale=st.floats(0.01, 100.0),
    offset=st.tuples(st.floats(-100.0, 100.0), st.floats(-100.0, 100.0)),
    start=st.integers(0, 100),
)
@settings(max_examples=50, deadline=None)
def test_invariance_under_similarity_restart_and_reversal(
    a: FloatArray,
    b: FloatArray,
    phi: float,
    scale: float,
    offset: tuple[float, float],
    start: int,
) -> None:
    expected = turning_distance(a, b)
    shift = np.array(offset)
    assert turning_distance(a + shift, b) == pytest.approx(expected, abs=NEAR_ZERO)
    assert turning_distance(rotate(a, phi), b) == pytest.approx(expected, abs=NEAR_ZERO)
    assert turning_distance(scale * a, b) == pytest.approx(expected, abs=NEAR_ZERO)
    assert turning_distance(np.roll(a, start, axis=0), b) == pytest.approx(expected, abs=NEAR_ZERO)
    assert turning_distance(a[::-1], b) == pytest.approx(expected, abs=NEAR_ZERO)
    assert turning_distance(a, b[::-1]) == pytest.approx(expected, abs=NEAR_ZERO)
    moved = scale * rotate(np.roll(a, start, axis=0)[::-1], phi) + shift
    assert turning_distance(a, moved) < NEAR_ZERO


@given(a=star_polygons(), b=star_polygons(), c=star_polygons())
@settings(max_examples=50, deadline=None)
def test_triangle_inequality(a: FloatArray, b: FloatArray, c: FloatArray) -> None:
    assert turning_distance(a, c) <= turning_distance(a, b) + turning_distance(b, c) + TIGHT


@given(a=star_polygons(), b=star_polygons(), duplicate=st.integers(0, 100))
@settings(max_examples=30, deadline=None)
def test_repeated_vertices_do_not_change_the_distance(
    a: FloatArray, b: FloatArray, duplicate: int
) -> None:
    k = duplicate % a.shape[0]
    padded = np.concatenate((a[: k + 1], a[k : k + 1], a[k:], a[:1]))
    assert turning_distance(padded, b) == pytest.approx(turning_distance(a, b), abs=TIGHT)


# --- exactness ------------------------------------------------------------------------------


# Two octagons a few tenths of a millimetre apart (hypothesis found them on a clean CI run).
_NEAR_A = np.array(
    [[0.669130606, 0.743144825], [0.0868240888, 0.492403877], [-0.307830738, 0.394005377],
     [-0.498782025, -0.0348782369], [-0.615661475, -0.788010754], [0.0868240888, -0.492403877],
     [0.669130606, -0.743144825], [0.5, -1.22464680e-16]]
)  # fmt: skip
_NEAR_B = np.array(
    [[0.669022494, 0.743242156], [0.0867047035, 0.492424912], [-0.307983556, 0.393885934],
     [-0.498762498, -0.0351563685], [-0.615107271, -0.788443432], [0.0872418973, -0.492330023],
     [0.669832988, -0.742511796], [0.5, -5.66553890e-16]]
)  # fmt: skip


@given(a=star_polygons(), b=star_polygons())
@example(a=_NEAR_A, b=_NEAR_B)
@settings(max_examples=30, deadline=None)
def test_agrees_with_dense_sampling_brute_force(a: FloatArray, b: FloatArray) -> None:
    """The sampled reference is off by its grid: each jump of either turning function (at most
    pi, one per vertex) lands up to a sample away, and the best shift is a multiple of one, each
    changing d^2 by at most jump^2 / samples. Compared on d^2 with that bound (on d it would be
    divided by 2 d: loose far from 0, too tight near it; two polygons a few tenths of a
    millimetre apart differed by 1.4e-3 on d with 65,536 samples, on a clean CI run)."""
    samples = 1 << 20
    exact = turning_distance(a, b)
    sampled = brute_force_distance(a, b, samples)
    bound = (len(a) + len(b)) * math.pi**2 / samples
    assert exact**2 == pytest.approx(sampled**2, abs=bound)


@given(a=star_polygons(max_vertices=25), b=star_polygons(max_vertices=25))
@settings(max_examples=30, deadline=None)
def test_windowed_sweep_matches_the_single_sweep(a: FloatArray, b: FloatArray) -> None:
    sa, fa = turning_function(a)
    sb, fb = turning_function(b)
    whole = _match_functions(sa, fa, sb, fb)
    for max_events in (7, sa.shape[0] * sb.shape[0] // 3 + 1):
        windowed = _match_functions(sa, fa, sb, fb, max_events=max_events)
        assert windowed.distance == pytest.approx(whole.distance, abs=TIGHT)
