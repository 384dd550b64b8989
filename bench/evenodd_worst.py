"""The scans that carry ICP's lead over RLuTF in the even/odd check, one by one.

Run: ``python -m bench.evenodd --worst [--logs intel,aces] [--write]``.

The even/odd check (:mod:`bench.evenodd`) pools each method's tracking errors into an RMSE,
which a few large errors dominate. Here each tracked odd scan's error of RLuTF (default
localizer, the map as ``rlutf map build`` writes it) is set beside ICP's on the raw points
(:data:`bench.evenodd_settle.ICP`), per odometry seed, and the scans where RLuTF's squared
error exceeds ICP's the most over the seeds are listed with what the map says about them: the
scan refined on the map from its corrected pose (*from the truth*) and from RLuTF's tracked
answer, each with the polar area between the scan and the map there (the localizer's own
measure, lower is better). Where the answer's area is lower than the truth's, the map itself
prefers the wrong place (no search or refinement can help: the walls or the scan are not what
the log's SLAM saw); where it is higher, the tracking settled in a worse basin than the one at
the truth (a wider search or a second start could find the truth's); within 2 % of each
other, neither. The RMSE of each method with the listed scans left out follows.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence

import numpy as np

from bench.evenodd_runs import ICP_SETTINGS, even_map, icp_method, odd_run, rlutf_method
from bench.evenodd_settle import ICP
from bench.methods import Method, track
from bench.scenarios import FloatArray
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map
from rlutf.problem import Problem
from rlutf.raycast import Beams
from rlutf.refine import refine_pose
from rlutf.scan import Scan

#: Scans listed per log.
WORST = 6


#: Areas within this share of each other: the map prefers neither.
SAME = 0.02


def _prefers(truth: float, answer: float) -> str:
    if abs(truth - answer) <= SAME * max(truth, answer):
        return "neither (within 2 %)"
    return "the answer" if answer < truth else "the truth"


def _errors(poses: FloatArray, truth: FloatArray) -> FloatArray:
    e = np.hypot(*(poses[:, :2] - truth[1:, :2]).T) * 100.0
    return np.where(np.isfinite(e), e, np.inf)


def refined(
    world: Map, scan: Scan, start: FloatArray, config: LocalizerConfig
) -> tuple[FloatArray, float]:
    """The scan refined on ``world`` from ``start`` as the localizer refines: (pose, area)."""
    problem = Problem(world, scan, config, Beams.of(scan.angles))
    fit = refine_pose(
        world, start, problem.beams, problem.real_ranges, problem.offset, problem.scan_range,
        config.refine_settings(), fit_distance=config.fit_distance, area=problem.area_terms(),
    )  # fmt: skip
    return np.asarray(fit.pose), float(fit.area_final)


def render_worst(
    logs: Sequence[str],
    seeds: Sequence[int],
    command: str,
    progress: Callable[[str], None] = lambda s: None,
) -> str:
    """The section: per log, the scans where RLuTF trails ICP most, and what the map says."""
    config = LocalizerConfig()
    out = [
        "### The scans that carry the difference",
        "",
        f"Command: `{command}`.",
        "",
        re.sub(r":\w+:`~?", "`", " ".join((__doc__ or "").split("\n\n")[2].split())).replace(
            "``", "`"
        ),
        "",
        f"Odometry seeds {', '.join(map(str, seeds))}.",
        "",
    ]
    for name in logs:
        world = even_map(name)
        ours, theirs, answers = [], [], []
        for seed in seeds:
            run = odd_run(name, world, seed)
            progress(f"{name}, seed {seed}: RLuTF and ICP")
            trace = track(rlutf_method(config), run, seed=seed)
            ours.append(_errors(trace.poses, run.truth))
            answers.append(trace.poses)
            icp: Method = icp_method(name, ICP_SETTINGS[ICP])
            theirs.append(_errors(track(icp, run, seed=seed).poses, run.truth))
        a, b = np.array(ours), np.array(theirs)
        excess = (np.minimum(a, 1e4) ** 2 - np.minimum(b, 1e4) ** 2).sum(axis=0)
        worst = [int(k) for k in np.argsort(-excess)[:WORST]]
        run = odd_run(name, world, seeds[0])
        rows = []
        for k in worst:
            scan, truth = run.scans[k + 1], run.truth[k + 1]
            at_truth, area_truth = refined(world, scan, truth, config)
            seed = int(np.argmax(a[:, k]))  # the seed where RLuTF is furthest off
            _, area_answer = refined(world, scan, answers[seed][k], config)
            off = math.hypot(*(at_truth[:2] - truth[:2])) * 100.0
            prefers = _prefers(area_truth, area_answer)
            rows.append(
                f"| {2 * (k + 1) + 1} | {' / '.join(f'{v:.1f}' for v in a[:, k])} | "
                f"{' / '.join(f'{v:.1f}' for v in b[:, k])} | {off:.1f} | "
                f"{area_truth:.4f} | {area_answer:.4f} | {prefers} |"
            )
        keep = np.ones(a.shape[1], dtype=bool)
        keep[worst] = False

        def rmse(e: FloatArray) -> float:
            return float(np.sqrt(np.mean(e**2)))

        out += [
            f"**{name}** (log scan number; errors in cm per seed; area: the polar area at the "
            "refined pose, from RLuTF's answer on the seed where it is furthest off):",
            "",
            "| scan | RLuTF cm | ICP cm | from the truth cm | area from the truth | "
            "area from the answer | the map prefers |",
            "| ---: | --- | --- | ---: | ---: | ---: | --- |",
            *rows,
            "",
            f"RMSE pooled over the seeds, RLuTF against ICP: {rmse(a.ravel()):.2f} against "
            f"{rmse(b.ravel()):.2f} cm; without these {len(worst)} scans: "
            f"{rmse(a[:, keep].ravel()):.2f} against {rmse(b[:, keep].ravel()):.2f} cm.",
            "",
        ]
    return "\n".join(out)
