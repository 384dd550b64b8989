import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rlutf.motion import (
    compose,
    interpolate,
    inverse,
    relative,
    transform_points,
    wrap_angle,
    wrap_scalar,
)

finite = st.floats(-50, 50, allow_nan=False)
angle = st.floats(-10, 10, allow_nan=False)
pose = st.tuples(finite, finite, angle).map(np.array)


def test_wrap_angle_range_and_values() -> None:
    a = wrap_angle([0.0, math.pi, -math.pi, 3 * math.pi, 7.0])
    assert np.all(a >= -math.pi) and np.all(a < math.pi)
    assert a[0] == 0.0
    assert a[1] == -math.pi
    assert math.isclose(a[4], 7.0 - 2 * math.pi)


def test_wrap_angle_just_under_pi_stays_in_range() -> None:
    just_under = math.nextafter(math.pi, 0.0)
    for a in (just_under, -math.pi - 1e-17, 3 * math.pi - 1e-15):
        w = float(wrap_angle(a))
        assert -math.pi <= w < math.pi
        assert -math.pi <= wrap_scalar(a) < math.pi


def test_compose_known_values() -> None:
    out = compose([1.0, 2.0, math.pi / 2], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(out, [1.0, 3.0, math.pi / 2], atol=1e-12)


@given(pose, pose)
@settings(max_examples=80, deadline=None)
def test_relative_inverts_compose(a: np.ndarray, b: np.ndarray) -> None:
    back = compose(a, relative(a, b))
    np.testing.assert_allclose(back[:2], b[:2], atol=1e-9)
    assert abs(wrap_angle(back[2] - b[2])) < 1e-9


@given(pose)
@settings(max_examples=50, deadline=None)
def test_inverse_is_identity(a: np.ndarray) -> None:
    np.testing.assert_allclose(compose(inverse(a), a), [0.0, 0.0, 0.0], atol=1e-9)


def test_batches_broadcast() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, math.pi]])
    out = compose(a, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(out[:, :2], [[1.0, 0.0], [0.0, 1.0]], atol=1e-12)


def test_transform_points_matches_compose() -> None:
    p = np.array([2.0, -1.0, 0.7])
    pts = np.array([[1.0, 0.0], [0.0, 2.0]])
    ref = np.array([compose(p, [x, y, 0.0])[:2] for x, y in pts])
    np.testing.assert_allclose(transform_points(p, pts), ref, atol=1e-12)


def test_interpolate_endpoints_and_middle() -> None:
    a = np.array([0.0, 0.0, 0.0])
    b = np.array([2.0, 0.0, 0.4])
    np.testing.assert_allclose(interpolate(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(interpolate(a, b, 1.0), b, atol=1e-12)
    assert math.isclose(float(interpolate(a, b, 0.5)[2]), 0.2)


@given(pose, pose, st.floats(0, 1))
@settings(max_examples=300, deadline=None)
def test_one_pose_path_gives_the_same_bits_as_the_batch_path(
    a: np.ndarray, b: np.ndarray, f: float
) -> None:
    # One (3,) pose takes plain float arithmetic; a (1, 3) batch takes numpy's ufuncs. Poses
    # must not change with the path (replay compares them bit for bit).
    batch_a, batch_b = a[None, :], b[None, :]
    assert compose(a, b).tobytes() == compose(batch_a, batch_b)[0].tobytes()
    assert inverse(a).tobytes() == inverse(batch_a)[0].tobytes()
    assert relative(a, b).tobytes() == relative(batch_a, batch_b)[0].tobytes()
    fast = interpolate(a, b, f)
    slow = compose(batch_a, relative(batch_a, batch_b) * f)[0]
    assert fast.tobytes() == slow.tobytes()


@given(pose, pose)
@settings(max_examples=300)
def test_the_localizers_float_compose_is_numpys_bit_for_bit(a: np.ndarray, b: np.ndarray) -> None:
    from rlutf.localizer import _compose

    assert _compose(a, b).tobytes() == compose(a[None], b[None])[0].tobytes()
