"""``rlutf map build`` shows its readings of the log as progress bars on a terminal
(``service.cli.buildprogress``), and the grid is the one built without them."""

from __future__ import annotations

import io
from collections.abc import Iterator

import numpy as np
from rich.console import Console

from service.cli.buildprogress import reading_scans
from service.maps.mapimport import build_grid

Scan = tuple[np.ndarray, np.ndarray, np.ndarray, float]


def _scans(n: int) -> list[Scan]:
    rng = np.random.default_rng(3)
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    return [
        (np.array([0.1 * i, 0.0, 0.05 * i]), rng.uniform(1.0, 3.0, 90), angles, 10.0)
        for i in range(n)
    ]


def _terminal() -> tuple[Console, io.StringIO]:
    out = io.StringIO()
    return Console(file=out, force_terminal=True, width=120), out


def test_each_reading_is_a_bar_and_the_grid_is_the_same() -> None:
    scans = _scans(40)
    console, out = _terminal()
    with reading_scans("site.mcap", console) as counted:
        grid = build_grid(counted(scans), resolution=0.05)
    shown = out.getvalue()
    assert "map build: site.mcap, scans for its extent" in shown
    assert "map build: site.mcap, scans for its cells" in shown
    assert "40/40" in shown
    plain = build_grid(scans, resolution=0.05)
    assert np.array_equal(grid.data, plain.data) and grid.origin == plain.origin


def test_scans_that_can_be_read_once_are_held_and_read_twice() -> None:
    scans = _scans(25)

    def once() -> Iterator[Scan]:
        yield from scans

    console, out = _terminal()
    with reading_scans("bag", console) as counted:
        grid = build_grid(counted(once()), resolution=0.05)
    assert "25/25" in out.getvalue()
    assert np.array_equal(grid.data, build_grid(scans, resolution=0.05).data)


def test_a_function_giving_the_scans_anew_is_called_each_reading() -> None:
    calls = []

    def anew() -> list[Scan]:
        calls.append(1)
        return _scans(10)

    console, _ = _terminal()
    with reading_scans("log", console) as counted:
        build_grid(counted(anew), resolution=0.05)
    assert len(calls) == 2  # never held: the extent, then the cells
