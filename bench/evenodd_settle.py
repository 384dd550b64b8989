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

import math
from collections.abc import Callable, Sequence

import numpy as np

from bench.baselines.icp import IcpConfig, PointToLineIcp
from bench.evenodd_runs import (
    ICP_SETTINGS,
    Errors,
    LeaveOutIcp,
    MapRecipe,
    even_map,
    odd_base,
    odd_run,
    raw_points,
)
from bench.scenarios import FloatArray
from bench.wallfit import WallFit
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map
from rlutf.problem import Problem
from rlutf.raycast import Beams
from rlutf.refine import refine_pose
from rlutf.scan import Scan

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

#: A refinement of scan ``k`` of the odd run from a start pose: the settled pose.
Refiner = Callable[[int, Scan, FloatArray], FloatArray]


def offsets(count: int) -> FloatArray:
    """``(count, STARTS, 3)`` start offsets, the same for every method."""
    rng = np.random.default_rng(SEED)
    scale = np.array([SIGMA_XY, SIGMA_XY, SIGMA_THETA])
    out: FloatArray = rng.normal(0.0, 1.0, (count, STARTS, 3)) * scale
    return out


def rlutf_refiner(world: Map) -> Refiner:
    """The localizer's refinement (default settings) on ``world``."""
    config = LocalizerConfig()
    settings = config.refine_settings()
    beams: list[Beams] = []

    def refine(k: int, scan: Scan, start: FloatArray) -> FloatArray:
        if not beams:
            beams.append(Beams.of(scan.angles))
        p = Problem(world, scan, config, beams[0])
        fit = refine_pose(
            world, start, p.beams, p.real_ranges, p.offset, p.scan_range, settings,
            fit_distance=config.fit_distance,
        )  # fmt: skip
        return np.asarray(fit.pose)

    return refine


def icp_refiner(name: str, config: IcpConfig, window: int = 0) -> Refiner:
    """ICP on the raw points (``window`` > 0: without the even scans around the scan)."""
    leave = LeaveOutIcp(name, odd_base(name).truth[0], config, window) if window else None

    def refine(k: int, scan: Scan, start: FloatArray) -> FloatArray:
        samples = raw_points(name) if leave is None else leave.samples_for(k)
        pose = PointToLineIcp(None, start, config, samples).update(np.zeros(3), scan).pose
        return np.full(3, np.inf) if pose is None else np.asarray(pose)

    return refine


def settle(name: str, refine: Refiner) -> tuple[Errors, Errors, float]:
    """Errors (cm) from the corrected pose itself and from the first offset start, and the
    median spread (cm) of the settled poses over :data:`STARTS` offsets."""
    run = odd_run(name, even_map(name))
    moves = offsets(len(run.scans))
    at_truth, moved, spread = [], [], []
    for k in range(1, len(run.scans)):
        truth = run.truth[k]
        at_truth.append(_cm_off(refine(k, run.scans[k], truth), truth))
        settled = np.array([refine(k, run.scans[k], truth + m) for m in moves[k]])
        moved.append(_cm_off(settled[0], truth))
        mean = settled.mean(axis=0)
        spread.append(float(np.median(np.hypot(*(settled[:, :2] - mean[:2]).T))) * 100.0)
    return Errors(np.asarray(at_truth)), Errors(np.asarray(moved)), float(np.median(spread))


def _cm_off(pose: FloatArray, truth: FloatArray) -> float:
    return math.hypot(*(pose[:2] - truth[:2])) * 100.0


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
    for name in logs:
        methods: list[tuple[str, Refiner]] = [
            ("RLuTF refinement on the built map", rlutf_refiner(even_map(name))),
            (
                "RLuTF refinement on the fitted walls (the built map moved onto the hits)",
                rlutf_refiner(even_map(name, MapRecipe(fit=WallFit(simplify=0.0)))),
            ),
            ("ICP on the raw points of every even scan", icp_refiner(name, cfg)),
            ("ICP on the raw points, window 1 left out", icp_refiner(name, cfg, 1)),
        ]
        for label, refine in methods:
            progress(f"{name}: {label}")
            at_truth, moved, spread = settle(name, refine)
            lines.append(
                f"| {name} | {label} | {moved.rmse:.2f} | {moved.percentile(50):.2f} | "
                f"{moved.percentile(95):.2f} | {at_truth.rmse:.2f} / "
                f"{at_truth.percentile(50):.2f} | {spread:.2f} |"
            )
    return "\n".join([*lines, ""])
