"""SE(2) poses: composition, inverse, relative motion and angle wrapping.

A pose is ``(x, y, theta)`` in metres and radians (REP 103: x forward, y left, theta
counter-clockwise). Functions accept a single pose of shape ``(3,)`` or a batch ``(..., 3)`` and
broadcast like numpy.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_TWO_PI = 2.0 * math.pi


def wrap_angle(angle: ArrayLike) -> FloatArray:
    """Wrap angles to ``[-pi, pi)``.

    Args:
        angle: angles in radians, any shape.

    Returns:
        The wrapped angles, same shape, float64.
    """
    a = np.asarray(angle, dtype=np.float64)
    out = np.asarray((a + math.pi) % _TWO_PI - math.pi, dtype=np.float64)
    # An angle just under pi can round to pi itself.
    return np.where(out >= math.pi, out - _TWO_PI, out)


def wrap_scalar(angle: float) -> float:
    """Wrap one angle to ``[-pi, pi)`` without numpy overhead."""
    out = (angle + math.pi) % _TWO_PI - math.pi
    return out - _TWO_PI if out >= math.pi else out


def _one_pose(p: ArrayLike) -> tuple[float, float, float] | None:
    """``p`` as three floats when it is one float64 pose ``(3,)``, else ``None``.

    One pose goes through plain float arithmetic: numpy's per-call overhead is ~1 us a ufunc,
    and ``relative`` of two poses took ~35 us that way, once per scan and robot. The float
    path does the same IEEE operations in the same order (``math.cos`` and ``numpy.cos`` give
    the same bits: tests/rlutf/test_motion.py checks both paths agree exactly).
    """
    if type(p) is np.ndarray and p.shape == (3,) and p.dtype == np.float64:
        x, y, th = p.tolist()
        return x, y, th
    return None


def _as_pose(p: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {arr.shape}")
    return arr


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Compose two poses: ``a (+) b``, pose ``b`` given in ``a``'s frame mapped to the world.

    Args:
        a: poses ``(..., 3)``.
        b: poses ``(..., 3)``, broadcast against ``a``.

    Returns:
        ``(..., 3)`` composed poses with the heading wrapped to ``[-pi, pi)``.
    """
    one_a, one_b = _one_pose(a), _one_pose(b)
    if one_a is not None and one_b is not None:
        ax, ay, ath = one_a
        bx, by, bth = one_b
        ca, sa = math.cos(ath), math.sin(ath)
        return np.array(
            [ax + ca * bx - sa * by, ay + sa * bx + ca * by, wrap_scalar(ath + bth)],
            dtype=np.float64,
        )
    pa = _as_pose(a, "a")
    pb = _as_pose(b, "b")
    c = np.cos(pa[..., 2])
    s = np.sin(pa[..., 2])
    x = pa[..., 0] + c * pb[..., 0] - s * pb[..., 1]
    y = pa[..., 1] + s * pb[..., 0] + c * pb[..., 1]
    th = wrap_angle(pa[..., 2] + pb[..., 2])
    return np.stack(np.broadcast_arrays(x, y, th), axis=-1)


def inverse(a: ArrayLike) -> FloatArray:
    """Inverse pose: ``inverse(a) (+) a == identity``.

    Args:
        a: poses ``(..., 3)``.

    Returns:
        ``(..., 3)`` inverse poses.
    """
    one = _one_pose(a)
    if one is not None:
        ax, ay, ath = one
        ca, sa = math.cos(ath), math.sin(ath)
        return np.array([-(ca * ax + sa * ay), -(-sa * ax + ca * ay), wrap_scalar(-ath)])
    pa = _as_pose(a, "a")
    c = np.cos(pa[..., 2])
    s = np.sin(pa[..., 2])
    x = -(c * pa[..., 0] + s * pa[..., 1])
    y = -(-s * pa[..., 0] + c * pa[..., 1])
    return np.stack([x, y, wrap_angle(-pa[..., 2])], axis=-1)


def relative(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Motion from pose ``a`` to pose ``b`` in ``a``'s frame: ``inverse(a) (+) b``.

    With two odometry readings this is the motion the robot reports between them, independent of
    where the odometry frame's origin is.

    Args:
        a: start poses ``(..., 3)``.
        b: end poses ``(..., 3)``.

    Returns:
        ``(..., 3)`` relative motions.
    """
    return compose(inverse(a), b)


def transform_points(pose: ArrayLike, points: ArrayLike) -> FloatArray:
    """Map points from a pose's local frame to the parent frame.

    Args:
        pose: one pose ``(3,)``.
        points: ``(N, 2)`` points in the pose's frame, metres.

    Returns:
        ``(N, 2)`` points in the parent frame.
    """
    p = _as_pose(pose, "pose")
    pts = np.asarray(points, dtype=np.float64)
    c, s = math.cos(float(p[2])), math.sin(float(p[2]))
    out = np.empty_like(pts)
    out[:, 0] = p[0] + c * pts[:, 0] - s * pts[:, 1]
    out[:, 1] = p[1] + s * pts[:, 0] + c * pts[:, 1]
    return out


def interpolate(a: ArrayLike, b: ArrayLike, fraction: float) -> FloatArray:
    """Interpolate between two poses along the relative motion (linear in x, y and heading).

    Args:
        a: start pose ``(3,)``.
        b: end pose ``(3,)``.
        fraction: 0 gives ``a``, 1 gives ``b``.

    Returns:
        ``(3,)`` interpolated pose.
    """
    d = relative(a, b)
    return compose(a, d * fraction)
