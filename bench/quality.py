"""Issue 23: calibration of the pose quality fields `deviation_range` and `localization_score`.

Run: ``python -m bench.quality [--steps N] [--seeds 1,2] [--kidnaps 1,2,3] [--write]``.

* **Coverage**: every simulated scenario of the accuracy benchmark (those whose data is
  present), each seed tracked by a :class:`rlutf.Localizer` with the default configuration from
  the true start pose; per update, whether the true position lies within the pose's
  ``deviation_range`` of its position (target: 90 to 99 % of the poses), and the range's median
  (target: under 5 cm).
* **Score**: the lowest score of a pose that is not ``lost``, the highest of one that is (must
  be under 0.5).
* **Kidnapping**: the runs of :func:`bench.relocalize.kidnap_run`'s setting (a robot teleported
  mid-run, its odometry seeing nothing): the scans from the kidnap until the score falls under
  0.5 (target: at most 3), and until it is back over 0.5 for good with the pose within 5 cm
  (recovered); the coverage of the range over the scans between.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bench.accuracy import has_data
from bench.kidnap import kidnap_path
from bench.reloccases import BUILDING_SIZES_KIDNAP
from bench.report import ints_text, section_main
from bench.scenarios import FloatArray, Run, named_scenarios, simulate
from rlutf.localizer import Localizer, LocalizeResult
from rlutf.motion import relative
from rlutf.sim import LidarModel, make_building, simulate_scan

SECTION = "quality"
COVERAGE_TARGET = (0.90, 0.99)
MEDIAN_TARGET = 0.05
KIDNAP_TARGET = 3
#: A kidnapped robot is found again when its pose is this close to the truth, metres.
FOUND = 0.05


@dataclass(frozen=True)
class Quality:
    """What the quality fields said over some updates, beside the truth.

    Attributes:
        errors: ``(U,)`` position error of each pose, metres.
        ranges: ``(U,)`` its deviation range, metres.
        scores: ``(U,)`` its localization score.
        lost: ``(U,)`` whether its status was ``lost``.
    """

    errors: FloatArray
    ranges: FloatArray
    scores: FloatArray
    lost: np.ndarray

    @property
    def coverage(self) -> float:
        """Share of the poses whose true position lies within their range."""
        return float(np.mean(self.errors <= self.ranges)) if len(self.errors) else math.nan

    @property
    def median_range(self) -> float:
        """Median range, metres."""
        return float(np.median(self.ranges)) if len(self.ranges) else math.nan

    @classmethod
    def of(cls, results: Sequence[LocalizeResult], truth: FloatArray) -> Quality:
        """The quality of ``results``, pose ``i`` graded against ``truth[i]``."""
        poses = np.array([r.pose[:2] for r in results]).reshape(-1, 2)
        return cls(
            np.hypot(*(poses - truth[:, :2]).T),
            np.array([r.deviation_range for r in results]),
            np.array([r.score for r in results]),
            np.array([r.status == "lost" for r in results], dtype=bool),
        )

    @staticmethod
    def join(parts: Sequence[Quality]) -> Quality:
        """Several runs pooled."""
        return Quality(
            np.concatenate([q.errors for q in parts]),
            np.concatenate([q.ranges for q in parts]),
            np.concatenate([q.scores for q in parts]),
            np.concatenate([q.lost for q in parts]),
        )


def track(run: Run) -> list[LocalizeResult]:
    """A default :class:`Localizer` over a run from its true start pose."""
    loc = Localizer(run.world, run.truth[0], seed=run.seed)
    return [
        loc.update(relative(run.odometry[k - 1], run.odometry[k]), run.scans[k])
        for k in range(1, len(run.scans))
    ]


@dataclass(frozen=True)
class Kidnap:
    """One kidnapped run: scans from the kidnap until the score fell under 0.5 (``None``:
    never), until it recovered (``None``: never), and the quality from the kidnap on."""

    seed: int
    to_low: int | None
    to_recovered: int | None
    quality: Quality


def kidnap(seed: int, steps: int, at: int) -> Kidnap:
    """A default :class:`Localizer` on a building, teleported at scan ``at``."""
    sizes = BUILDING_SIZES_KIDNAP[seed % len(BUILDING_SIZES_KIDNAP)]
    world = make_building(np.random.default_rng(seed), *sizes)
    truth, odometry = kidnap_path(world, seed, steps, at)
    scan_rng = np.random.default_rng([seed, 3])
    scans = [simulate_scan(world, truth[k], LidarModel(), scan_rng) for k in range(steps)]
    loc = Localizer(world, truth[0], seed=seed)
    results = [
        loc.update(relative(odometry[k - 1], odometry[k]), scans[k]) for k in range(1, steps)
    ]
    after = Quality.of(results[at - 1 :], truth[at:])
    low = np.flatnonzero(after.scores < 0.5)
    good = (after.scores >= 0.5) & (after.errors < FOUND)
    recovered = next((i + 1 for i in range(len(good)) if good[i:].all()), None)
    return Kidnap(seed, int(low[0]) + 1 if len(low) else None, recovered, after)


def _pct(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{100.0 * v:.1f} %"


def _cm(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{100.0 * v:.2f}"


def coverage_table(rows: Sequence[tuple[str, Quality]]) -> list[str]:
    """One row per scenario and one for all pooled."""
    out = [
        "| scenario | poses | within range | median range cm | median error cm | "
        "p95 error / range | lost | lowest score (not lost) | highest score (lost) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, q in [*rows, ("all", Quality.join([q for _, q in rows]))]:
        ratio = q.errors / np.maximum(q.ranges, 1e-12)
        kept, lost = q.scores[~q.lost], q.scores[q.lost]
        out.append(
            f"| {name} | {len(q.errors)} | {_pct(q.coverage)} | {_cm(q.median_range)} | "
            f"{_cm(float(np.median(q.errors)))} | {np.percentile(ratio, 95):.2f} | "
            f"{int(q.lost.sum())} | {f'{kept.min():.3f}' if len(kept) else '-'} | "
            f"{f'{lost.max():.3f}' if len(lost) else '-'} |"
        )
    return out


def kidnap_table(runs: Sequence[Kidnap]) -> list[str]:
    """One row per kidnapped run."""
    out = [
        "| seed | scans until score < 0.5 | scans until recovered | within range (from the "
        "kidnap) | highest score over 0.3 m off |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    for k in runs:
        far = k.quality.scores[k.quality.errors > 0.3]
        out.append(
            f"| {k.seed} | {k.to_low if k.to_low is not None else 'never'} | "
            f"{k.to_recovered if k.to_recovered is not None else 'never'} | "
            f"{_pct(k.quality.coverage)} | {f'{far.max():.3f}' if len(far) else '-'} |"
        )
    return out


def render(steps: int, seeds: Sequence[int], kidnaps: Sequence[int], command: str) -> str:
    """The section of ``BENCHMARKS.md``."""
    rows: list[tuple[str, Quality]] = []
    for scenario in named_scenarios(steps):
        if not has_data(scenario.world):
            continue
        parts = []
        for seed in seeds:
            run = simulate(scenario, seed)
            parts.append(Quality.of(track(run), run.truth[1:]))
        rows.append((scenario.name, Quality.join(parts)))
    pooled = Quality.join([q for _, q in rows])
    runs = [kidnap(seed, 160, 80) for seed in kidnaps]
    lows = [k.to_low for k in runs]
    worst_low = max((v if v is not None else 10**9) for v in lows) if runs else 0
    everything = Quality.join([pooled, *(k.quality for k in runs)])
    lost_scores = everything.scores[everything.lost]
    lines = [
        "## Pose quality: deviation range and localization score (issue 23)",
        "",
        f"Command: `{command}`. Default `LocalizerConfig`, each simulated scenario's runs "
        f"({steps} scans, seeds {', '.join(map(str, seeds))}) tracked from the true start pose; "
        "a pose's range covers the truth when its position error is at most its "
        "`deviation_range`. The kidnapped runs are the relocalization benchmark's setting "
        "(`bench.relocalize.kidnap_path`: 160 scans, teleported at scan 80, the odometry "
        "seeing nothing); recovered: score at least 0.5 and the pose within 5 cm from then on.",
        "",
        "| target | measured | met |",
        "| --- | --- | --- |",
        f"| truth within `deviation_range` for 90-99 % of poses | {_pct(pooled.coverage)} "
        f"(scenarios {_pct(min(q.coverage for _, q in rows))} to "
        f"{_pct(max(q.coverage for _, q in rows))}) | "
        f"{'yes' if COVERAGE_TARGET[0] <= pooled.coverage <= COVERAGE_TARGET[1] else 'no'} |",
        f"| median `deviation_range` under 5 cm | {_cm(pooled.median_range)} cm | "
        f"{'yes' if pooled.median_range < MEDIAN_TARGET else 'no'} |",
        f"| `lost` implies a score under 0.5 | highest score of the {len(lost_scores)} lost "
        f"poses (scenarios and kidnapped runs) "
        f"{f'{lost_scores.max():.3f}' if len(lost_scores) else '-'} | "
        f"{'yes' if not len(lost_scores) or lost_scores.max() < 0.5 else 'no'} |",
        f"| kidnapped: score under 0.5 within 3 scans | "
        f"{', '.join('never' if v is None else str(v) for v in lows)} scans | "
        f"{'yes' if worst_low <= KIDNAP_TARGET else 'no'} |",
        f"| kidnapped: score recovers when found | "
        f"{', '.join('never' if k.to_recovered is None else str(k.to_recovered) for k in runs)}"
        f" scans | {'yes' if all(k.to_recovered is not None for k in runs) else 'no'} |",
        "",
        *coverage_table(rows),
        "",
        *kidnap_table(runs),
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    parser = argparse.ArgumentParser(prog="python -m bench.quality", description=__doc__)
    parser.add_argument("--steps", type=int, default=250, help="scans per simulated run")
    parser.add_argument(
        "--seeds", type=ints_text(0), default="1,2", help="seeds of each scenario's runs"
    )
    parser.add_argument(
        "--kidnaps", type=ints_text(0), default="1,2,3,4,5,6", help="seeds of the kidnapped runs"
    )
    args_list = list(argv) if argv is not None else sys.argv[1:]

    def run(args: argparse.Namespace) -> str:
        seeds = [int(s) for s in args.seeds.split(",") if s]
        kidnaps = [int(s) for s in args.kidnaps.split(",") if s]
        shown = " ".join(["python -m bench.quality", *args_list])
        return render(args.steps, seeds, kidnaps, shown.replace(" --write", ""))

    return section_main(parser, run, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
