"""The scans that carry the difference (``python -m bench.evenodd --worst``): the refinement it
classifies them with, on a drawn room (the section itself runs on the CARMEN logs)."""

from __future__ import annotations

import numpy as np
from shapely.geometry import box

from bench.evenodd_worst import refined
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map
from rlutf.raycast import cast_rays
from rlutf.scan import Scan

ROOM = box(0, 0, 6, 4).difference(box(4, 2, 6, 4))  # L-shaped: no symmetry


def _scan(world: Map, pose: np.ndarray) -> Scan:
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    ranges = cast_rays(world, pose, angles, 10.0)[0]
    return Scan.create(ranges, float(angles[0]), float(angles[1] - angles[0]), 0.05, 10.0)


def test_the_area_is_lower_where_the_map_explains_the_scan() -> None:
    world = Map.from_shapely(ROOM)
    truth = np.array([2.0, 1.5, 0.4])
    scan = _scan(world, truth)
    pose, area = refined(world, scan, truth, LocalizerConfig())
    assert np.hypot(*(pose[:2] - truth[:2])) < 1e-3 and area < 1e-3
    # the same scan against walls 20 cm off explains it worse from anywhere near
    moved = Map.from_shapely(box(0, 0, 6, 4.2).difference(box(4, 2.2, 6, 4.2)))
    _, worse = refined(moved, scan, truth, LocalizerConfig())
    assert worse > area


def test_the_option_names_its_section_in_the_command() -> None:
    from bench.evenodd import _command

    args = type("A", (), {})()
    for name, value in (
        ("logs", "intel,aces"),
        ("seeds", 3),
        ("neighbours", False),
        ("cost", False),
        ("coarse", False),
        ("fitted", False),
        ("settle", False),
        ("worst", True),
        ("variants", True),
    ):
        setattr(args, name, value)
    assert _command(args) == "python -m bench.evenodd --worst --write"
