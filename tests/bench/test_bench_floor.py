"""bench.floor runs the three layers on a small fleet: the localizer, the engine, a real worker
process behind its pipe (the service's own worker protocol), each with a CPU figure per scan."""

from __future__ import annotations

import argparse
import math
import re

from bench.floor import render


def test_floor_measures_every_layer_through_a_real_worker() -> None:
    text = render(argparse.Namespace(robots=2, steps=60))
    rows = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 5  # header and the four layers
    figures = [float(re.split(r"\s*\|\s*", r)[2]) for r in rows[1:]]
    assert all(math.isfinite(x) and x >= 0 for x in figures), text
    assert figures[2] > 0, text  # the worker answered every batch (its CPU: clock ticks of 10 ms)
    assert "80 scans measured per row" in text
