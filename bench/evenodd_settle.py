"""Where a refinement settles on the maps of :mod:`bench.evenodd`, apart from tracking.

Run: ``python -m bench.evenodd --settle [--logs intel,aces] [--write]``.

The even/odd check's *from reference* column refines each odd scan once from its corrected pose
itself. A refinement started at the answer can stop close to it without that point being the
bottom of its cost, so that column says little about what a map allows. Here each odd scan is
refined from its corrected pose moved by a random offset (:data:`SIGMA_XY` in x and y,
:data:`SIGMA_THETA` in heading; the same offsets for every method, :data:`SEED`), no odometry
and no tracking involved: the error is where the method's cost settles near the truth. From
:data:`STARTS` such offsets per scan, *spread* is the median distance of the settled poses from
their mean (how much of the error is where the refinement started rather than where the cost's
bottom is).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from bench.evenodd_runs import (
    ICP_SETTINGS,
    Errors,
    MapRecipe,
    Refiner,
    at_reference,
    even_map,
    icp_refiner,
    odd_run,
    rlutf_refiner,
)
from bench.scenarios import FloatArray
from bench.wallfit import WallFit
from rlutf.localizer import LocalizerConfig

#: Standard deviation of the start's offset in x and in y, metres (a tracking prediction's
#: typical error on these logs: a few centimetres).
SIGMA_XY = 0.03
#: Standard deviation of the start's offset in heading, radians.
SIGMA_THETA = 0.015
#: Offsets per scan (the first gives the error columns; all of them the spread).
STARTS = 4
#: Seed of the offsets.
SEED = 11
#: ICP settings (the best of :data:`bench.evenodd_runs.ICP_SETTINGS` on both logs).
ICP = "gate 2 m to 0.2 m, 50 steps"


def offsets(count: int) -> FloatArray:
    """``(count, STARTS, 3)`` start offsets, the same for every method."""
    rng = np.random.default_rng(SEED)
    scale = np.array([SIGMA_XY, SIGMA_XY, SIGMA_THETA])
    out: FloatArray = rng.normal(0.0, 1.0, (count, STARTS, 3)) * scale
    return out


def settle(name: str, refine: Refiner) -> tuple[Errors, Errors, float, FloatArray]:
    """Errors (cm) from the corrected pose itself and from the first offset start, the median
    spread (cm) of the settled poses over :data:`STARTS` offsets, and ``(n, 2)`` the settled
    positions from the first offset less the corrected ones (m; ``inf`` where it failed)."""
    run = odd_run(name, even_map(name))
    moves = offsets(len(run.scans))
    spread, off = [], []
    for k in range(1, len(run.scans)):
        truth = run.truth[k]
        settled = np.array([refine(k, run.scans[k], truth + m) for m in moves[k]])
        off.append(settled[0, :2] - truth[:2])
        mean = settled.mean(axis=0)
        spread.append(float(np.median(np.hypot(*(settled[:, :2] - mean[:2]).T))) * 100.0)
    first = np.array(off)
    moved = Errors(np.hypot(*first.T) * 100.0)
    return at_reference(run, refine), moved, float(np.median(spread)), first


def correlation(a: FloatArray, b: FloatArray) -> tuple[float, float]:
    """Pearson correlation of two ``(n, 2)`` error sets in x and in y, over the rows where both
    are finite."""
    both = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    cx = float(np.corrcoef(a[both, 0], b[both, 0])[0, 1])
    cy = float(np.corrcoef(a[both, 1], b[both, 1])[0, 1])
    return cx, cy


def render_settle(
    logs: Sequence[str], command: str, progress: Callable[[str], None] = lambda s: None
) -> str:
    """The section's Markdown."""
    lines = [
        "### Where each refinement settles, apart from tracking",
        "",
        f"Command: `{command}`.",
        "",
        "Each odd scan refined once, with no odometry and no tracking, from its corrected pose "
        f"moved by a random offset ({SIGMA_XY * 100:g} cm standard deviation in x and y, "
        f"{SIGMA_THETA:g} rad in heading; the same offsets for every method). *At the corrected "
        "pose*: started at the corrected pose itself (the *from reference* column above). "
        f"*Spread*: from {STARTS} offsets per scan, the median distance of the settled poses "
        "from their mean. ICP settings: "
        f"{ICP}. Module `bench.evenodd_settle`.",
        "",
        "| log | method | from an offset start: RMSE cm | median cm | p95 cm | at the corrected "
        "pose: RMSE / median cm | spread cm |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    cfg = ICP_SETTINGS[ICP]
    config = LocalizerConfig()
    notes: list[str] = []
    for name in logs:
        methods: list[tuple[str, Refiner]] = [
            ("RLuTF refinement on the built map", rlutf_refiner(even_map(name), config)),
            (
                "RLuTF refinement on the fitted walls (the built map moved onto the hits)",
                rlutf_refiner(even_map(name, MapRecipe(fit=WallFit(simplify=0.0))), config),
            ),
            ("ICP on the raw points of every even scan", icp_refiner(name, cfg)),
            ("ICP on the raw points, window 1 left out", icp_refiner(name, cfg, 1)),
        ]
        errors: list[FloatArray] = []
        medians: list[float] = []
        for label, refine in methods:
            progress(f"{name}: {label}")
            at_truth, moved, spread, off = settle(name, refine)
            errors.append(off)
            medians.append(moved.percentile(50))
            lines.append(
                f"| {name} | {label} | {moved.rmse:.2f} | {moved.percentile(50):.2f} | "
                f"{moved.percentile(95):.2f} | {at_truth.rmse:.2f} / "
                f"{at_truth.percentile(50):.2f} | {spread:.2f} |"
            )
        both = Errors(np.hypot(*((errors[0] + errors[2]) / 2.0).T) * 100.0)
        lines.append(
            f"| {name} | the mean of the first and the third rows' settled poses | "
            f"{both.rmse:.2f} | {both.percentile(50):.2f} | {both.percentile(95):.2f} | - | - |"
        )
        cx, cy = correlation(errors[0], errors[2])
        rlutf_median, icp_median = medians[0], medians[2]
        closer = both.percentile(50) < min(rlutf_median, icp_median)
        notes.append(
            f"{name}: {cx:.2f} in x and {cy:.2f} in y, and their mean settles "
            + ("closer than either" if closer else "no closer than the better of the two")
            + f" (median {both.percentile(50):.2f} cm against {rlutf_median:.2f} and "
            f"{icp_median:.2f})"
        )
    return "\n".join(
        [
            *lines,
            "",
            "How the methods' errors go together: the settled position less the corrected one, "
            "from the first offset, of RLuTF on the built map and of ICP on the raw points of "
            f"every even scan, correlate (Pearson, over the scans) {'; '.join(notes)}. The two "
            "share the scan (its noise, the people in it) and the corrected pose they are "
            "measured against (the log's SLAM estimate, itself 1 to 3 cm off).",
            "",
        ]
    )
