import math

import numpy as np
import pytest

from rlutf.errors import GeometryError
from rlutf.scan import Scan, beam_points, needs_origin, simplify_ring


def test_no_return_rule() -> None:
    s = Scan.create([1.0, None, 0.01, 20.0, float("nan"), 3.0], -1.0, 0.1, 0.05, 12.0)
    assert s.valid().tolist() == [True, False, False, False, False, True]
    np.testing.assert_allclose(s.angles, -1.0 + 0.1 * np.arange(6))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"angle_increment": 0.0}, "angle_increment"),
        ({"range_min": 5.0, "range_max": 1.0}, "range_min"),
        ({"angle_min": float("inf")}, "finite"),
    ],
)
def test_bad_geometry(kwargs: dict, message: str) -> None:
    base = {"angle_min": 0.0, "angle_increment": 0.1, "range_min": 0.0, "range_max": 10.0}
    base.update(kwargs)
    with pytest.raises(GeometryError, match=message):
        Scan.create([1.0, 2.0], **base)


def test_sensor_offset_is_applied() -> None:
    pts = beam_points(
        np.array([1.0]), np.array([1.0]), np.array([0.0]), np.array([0.5, 0.0, math.pi / 2])
    )
    np.testing.assert_allclose(pts, [[0.5, 1.0]], atol=1e-12)


def test_polygon_closes_through_sensor_when_field_of_view_is_partial() -> None:
    full = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    assert not needs_origin(full, True, 0.35)
    assert needs_origin(full[:180], False, 0.35)
    gap = np.concatenate([full[:100], full[200:]])
    assert needs_origin(gap, True, 0.35)


def test_simplify_removes_noise_and_keeps_anchor() -> None:
    rng = np.random.default_rng(0)
    x = np.linspace(0, 4, 200)
    wall = np.column_stack([x, 1.0 + rng.normal(0, 0.01, len(x))])
    ring = np.vstack([wall, [[4.0, 3.0], [0.0, 3.0]]])
    out = simplify_ring(ring, 0.03)
    assert len(out) < 12
    np.testing.assert_array_equal(out[0], ring[0])


def test_valid_rejects_infinities_and_given_gaps_agree() -> None:
    s = Scan.create([float("inf"), -float("inf"), 2.0, 12.0, 0.05], 0.0, 0.1, 0.05, 12.0)
    assert s.valid().tolist() == [False, False, True, True, True]
    full = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    gap = np.concatenate([full[:100], full[200:]])
    for angles in (full, gap, full[:180]):
        gaps = np.abs(np.diff(angles))
        for fc in (True, False):
            assert needs_origin(angles, fc, 0.35, gaps) == needs_origin(angles, fc, 0.35)
