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


def test_time_in_the_kernels_is_part_of_each_update_and_the_kernels_come_back() -> None:
    import rlutf._lm as lm

    refine = lm.refine
    plan, _ = _fleet(3, 40)
    compiled: dict[int, list[float]] = {}
    costs = update_costs(plan, 40, compiled)
    assert compiled.keys() == costs.keys()
    for casts, totals in costs.items():
        inside = compiled[casts]
        assert len(inside) == len(totals)
        # every tracking update refines: some of it runs in the kernels, never more than all
        assert all(0 < k <= t for k, t in zip(inside, totals, strict=True)), (casts, inside)
    assert lm.refine is refine  # numba's dispatcher is back once the block ends


def test_only_the_kernels_python_calls_are_wrapped() -> None:
    import rlutf._kernels as kernels
    import rlutf._lm as lm
    from bench.floor import in_kernels

    spent = [0]
    with in_kernels(spent):
        assert not hasattr(lm.refine, "py_func")  # wrapped: Python calls it
        assert hasattr(kernels.cast_ray, "py_func")  # a kernel calls it: numba's own
        assert hasattr(lm._cost, "py_func")
    assert hasattr(lm.refine, "py_func")
