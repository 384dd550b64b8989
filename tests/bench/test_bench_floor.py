"""bench.floor runs the three layers on a small fleet: the localizer, the engine, a real worker
process behind its pipe (the service's own worker protocol), each with a CPU figure per scan."""

from __future__ import annotations

import argparse
import math
import re

from bench.floor import _fleet, cost_fit, render, update_costs


def test_floor_measures_every_layer_through_a_real_worker() -> None:
    text = render(argparse.Namespace(robots=2, steps=60))
    layers = text.split("The tracking updates")[0]
    rows = [line for line in layers.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 5  # header and the four layers
    figures = [float(re.split(r"\s*\|\s*", r)[2]) for r in rows[1:]]
    assert all(math.isfinite(x) and x >= 0 for x in figures), text
    assert figures[2] > 0, text  # the worker answered every batch (its CPU: clock ticks of 10 ms)
    assert "80 scans measured per row" in text


def test_update_costs_grow_with_casts_and_the_line_splits_them() -> None:
    plan, _ = _fleet(3, 60)
    costs = update_costs(plan, 60)
    assert sum(len(v) for v in costs.values()) > 60  # most updates track without a search
    assert all(c >= 1 and all(x > 0 for x in v) for c, v in costs.items())
    fixed, per_cast = cost_fit({2: [100.0, 100.0, 500.0], 3: [130.0], 4: [160.0, 161.0, 159.0]})
    assert math.isclose(per_cast, 30.0, rel_tol=1e-9) and math.isclose(fixed, 40.0, rel_tol=1e-9)
    assert all(math.isnan(x) for x in cost_fit({3: [1.0, 2.0]}))
