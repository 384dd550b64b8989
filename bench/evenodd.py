"""Maps from logs that match the log: the even scans build the map, the odd scans are tracked.

Run: ``python -m bench.evenodd [--logs intel,aces] [--seeds 3] [--no-variants] [--write]``.

The check an outside user makes of ``rlutf map build`` on a public CARMEN log: the even scans
(0, 2, 4, ...) at their corrected poses build the map as ``rlutf map build`` does
(:func:`service.maps.mapimport.build_grid` with its defaults, then
:func:`service.maps.mapimport.grid_to_map` with the built-map surface offset,
:data:`service.maps.mapimport.BUILT_SURFACE_CELLS`); the odd scans are tracked on it from the
first odd scan's corrected pose, with odometry made from the corrected poses' increments with
5 % noise on translation and rotation and a heading bias of 0.02 rad/m
(:data:`bench.carmen.ODOM5`, one seed per run). The baseline is point-to-line ICP whose map is
the even scans' raw points, one per 2 cm cell (:func:`bench.baselines.icp.point_samples`): the
log itself rather than the polygons traced from it. ICP on the polygon map (the accuracy
benchmark's baseline) is shown beside it. Errors are against the corrected poses (the SLAM
estimate, itself 1 to 3 cm off).

Per method: tracking RMSE of position over every update of every seed (cm), the median of the
per-scan errors, the 95th percentile, the largest, and the share of updates over 0.5 m off.
The variants table changes one thing at a time against the default map and localizer and also
gives each one's error when every odd scan is refined once from its corrected pose (no
tracking): what the map allows when the basin is not in question.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cache

import numpy as np

from bench.baselines.icp import IcpConfig, PointToLineIcp, WallSamples, point_samples
from bench.carmen import ODOM5_SEED, RANGE_MAX, carmen_run, slam_odometry
from bench.methods import Method, RlutfTracker, Trace, track
from bench.report import section_main
from bench.scenarios import DATA, FloatArray, Run
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map
from rlutf.problem import Problem
from rlutf.raycast import Beams
from rlutf.refine import refine_pose

SECTION = "evenodd"
LOGS = ("intel", "aces")
#: Updates further off than this count as diverged, metres.
DIVERGED_M = 0.5
#: The raw points' thinning, metres.
RAW_SPACING = 0.02
#: ICP settings on the raw points: the accuracy benchmark's, and two with a wider first gate
#: (the odd scans are up to 2 m and 80 degrees apart, the prediction up to 0.3 m off).
ICP_SETTINGS: dict[str, IcpConfig] = {
    "bench settings": IcpConfig(),
    "gate 1 m, Huber 5 cm, 50 steps": IcpConfig(max_iterations=50, max_distance=1.0, huber=0.05),
    "gate 2 m to 0.2 m, 50 steps": IcpConfig(max_iterations=50, max_distance=2.0, min_distance=0.2),
}


@dataclass(frozen=True)
class MapRecipe:
    """How the map is built from the even scans (the defaults are ``rlutf map build``'s).

    Attributes:
        resolution: cell size, metres.
        surface_cells: walls moved this many cells into the occupied cells.
        simplify: Douglas-Peucker tolerance, metres; ``None``: half a cell.
        free_thresh: hit ratio under which a cell is free.
        occupied_thresh: hit ratio over which a cell is occupied (cells in between are
            unknown, and unknown cells are walls).
    """

    resolution: float = 0.05
    surface_cells: float = 0.4
    simplify: float | None = None
    free_thresh: float = 0.25
    occupied_thresh: float = 0.65


@dataclass(frozen=True)
class Variant:
    """One row of the variants table: a map recipe and localizer settings."""

    label: str
    recipe: MapRecipe = field(default_factory=MapRecipe)
    config: LocalizerConfig = field(default_factory=LocalizerConfig)


def variants() -> list[Variant]:
    """The default, then one change at a time."""
    base = MapRecipe()
    return [
        Variant("default (as `rlutf map build` writes it, `LocalizerConfig()`)"),
        Variant("walls at the cell edges (surface offset 0)", replace(base, surface_cells=0.0)),
        Variant("surface offset 0.2 cell", replace(base, surface_cells=0.2)),
        Variant("surface offset 0.45 cell", replace(base, surface_cells=0.45)),
        Variant("simplify 0.25 cell", replace(base, simplify=0.0125)),
        Variant("simplify 1 cell", replace(base, simplify=0.05)),
        Variant("cells 2.5 cm", replace(base, resolution=0.025)),
        Variant("cells 4 cm", replace(base, resolution=0.04)),
        Variant(
            "no unknown band (free under 0.5, occupied over 0.5)",
            replace(base, free_thresh=0.5, occupied_thresh=0.5),
        ),
        Variant("refinement: 30 casts", config=LocalizerConfig(refine_iterations=30)),
        Variant("refinement: noise floor 1 cm", config=LocalizerConfig(noise_min=0.01)),
        Variant("refinement: incidence up to 60 deg", config=LocalizerConfig(max_incidence=1.047)),
    ]


def log_path(name: str) -> str:
    """The CARMEN log of ``name`` (``DATA/carmen/{name}-corrected.log.gz``)."""
    return str(DATA / "carmen" / f"{name}-corrected.log.gz")


@cache
def _even_scans(name: str) -> tuple:  # type: ignore[type-arg]
    from service.maps.mapimport import read_carmen

    return read_carmen(log_path(name)).scans[0::2]


@cache
def even_map(name: str, recipe: MapRecipe = MapRecipe()) -> Map:
    """The map of ``name``'s even scans, built as ``rlutf map build`` builds a log's."""
    from service.maps.mapimport import build_grid, grid_to_map

    grid = build_grid(
        _even_scans(name),
        resolution=recipe.resolution,
        free_thresh=recipe.free_thresh,
        occupied_thresh=recipe.occupied_thresh,
    )
    offset = recipe.surface_cells * recipe.resolution
    built = grid_to_map(grid, map_id=name, surface_offset=offset, simplify=recipe.simplify)
    return Map.from_geojson(built.map["geometry"])


@cache
def raw_points(name: str, spacing: float = RAW_SPACING) -> WallSamples:
    """The even scans' end points at their corrected poses, one per ``spacing`` cell."""
    points, sensors = [], []
    for s in _even_scans(name):
        ok = np.isfinite(s.ranges) & (s.ranges > 0.0) & (s.ranges < RANGE_MAX)
        heading = s.pose[2] + s.angles[ok]
        ends = s.pose[:2] + s.ranges[ok, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        points.append(ends)
        sensors.append(np.broadcast_to(s.pose[:2], ends.shape))
    return point_samples(np.vstack(points), np.vstack(sensors), spacing)


@cache
def _odd_base(name: str) -> Run:
    run = carmen_run(name, world=even_map(name))
    odd = np.arange(1, len(run.scans), 2)
    return replace(
        run,
        scenario=f"{name}-odd",
        stamps_ns=run.stamps_ns[odd],
        truth=run.truth[odd],
        odometry=run.odometry[odd],
        scans=tuple(run.scans[i] for i in odd),
    )


def odd_run(name: str, world: Map, seed: int = ODOM5_SEED) -> Run:
    """The odd scans of ``name`` on ``world``, odometry from :data:`bench.carmen.ODOM5`."""
    base = _odd_base(name)
    return replace(base, seed=seed, world=world, odometry=slam_odometry(base.truth, seed=seed))


@dataclass(frozen=True)
class Errors:
    """Position errors of one method over its runs, cm."""

    errors: FloatArray

    @property
    def rmse(self) -> float:
        """Root mean square."""
        return float(np.sqrt(np.mean(self.errors**2)))

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile."""
        return float(np.percentile(self.errors, q))

    @property
    def diverged(self) -> float:
        """Share of updates over :data:`DIVERGED_M` off."""
        return float(np.mean(self.errors > 100.0 * DIVERGED_M))


def _errors(trace: Trace, run: Run) -> FloatArray:
    e = np.hypot(*(trace.poses[:, :2] - run.truth[1:, :2]).T) * 100.0
    return np.where(np.isfinite(e), e, np.inf)


def rlutf_method(config: LocalizerConfig) -> Method:
    """RLuTF with ``config`` as a tracking method."""
    return Method("rlutf", "RLuTF", lambda w, p, s: RlutfTracker(w, p, config, s))


def icp_method(name: str, config: IcpConfig) -> Method:
    """Point-to-line ICP on ``name``'s raw even-scan points."""
    samples = raw_points(name)
    return Method("icp-raw", "ICP", lambda w, p, s: PointToLineIcp(None, p, config, samples))


def tracked(method: Method, name: str, world: Map, seeds: Sequence[int]) -> Errors:
    """``method`` tracking ``name``'s odd scans on ``world``, errors pooled over ``seeds``."""
    out = []
    for seed in seeds:
        run = odd_run(name, world, seed)
        out.append(_errors(track(method, run, seed=seed), run))
    return Errors(np.concatenate(out))


def from_reference(name: str, world: Map, config: LocalizerConfig) -> Errors:
    """Each odd scan refined once from its corrected pose on ``world`` (no tracking)."""
    run = odd_run(name, world)
    beams = Beams.of(run.scans[0].angles)
    settings = config.refine_settings()
    out = []
    for k in range(1, len(run.scans)):
        problem = Problem(world, run.scans[k], config, beams)
        fit = refine_pose(
            world, run.truth[k], problem.beams, problem.real_ranges, problem.offset,
            problem.scan_range, settings, fit_distance=config.fit_distance,
        )  # fmt: skip
        out.append(math.hypot(*(fit.pose[:2] - run.truth[k, :2])) * 100.0)
    return Errors(np.asarray(out))


def icp_from_reference(name: str, config: IcpConfig) -> Errors:
    """ICP on the raw points, each odd scan aligned once from its corrected pose."""
    run = _odd_base(name)
    samples = raw_points(name)
    out = []
    for k in range(1, len(run.scans)):
        pose = (
            PointToLineIcp(None, run.truth[k], config, samples)
            .update(np.zeros(3), run.scans[k])
            .pose
        )
        out.append(math.inf if pose is None else math.hypot(*(pose[:2] - run.truth[k, :2])) * 100)
    return Errors(np.asarray(out))


def _cm(v: float) -> str:
    return "inf" if not math.isfinite(v) else (f"{v:.2f}" if v < 10 else f"{v:.1f}")


def _row(label: str, e: Errors) -> str:
    return (
        f"| {label} | {_cm(e.rmse)} | {_cm(e.percentile(50))} | {_cm(e.percentile(95))} | "
        f"{_cm(float(e.errors.max()))} | {100 * e.diverged:.1f} % |"
    )


def render(args: argparse.Namespace, progress: Callable[[str], None] = lambda s: None) -> str:
    """Run the check and return the Markdown section."""
    logs = [s for s in args.logs.split(",") if s]
    seeds = [ODOM5_SEED + i for i in range(args.seeds)]
    default = LocalizerConfig()
    lines: list[str] = []
    targets: list[str] = []
    for name in logs:
        world = even_map(name)
        progress(f"{name}: RLuTF default")
        ours = tracked(rlutf_method(default), name, world, seeds)
        icps = {}
        for label, cfg in ICP_SETTINGS.items():
            progress(f"{name}: ICP {label}")
            icps[label] = tracked(icp_method(name, cfg), name, world, seeds)
        progress(f"{name}: ICP on the polygon map")
        poly = tracked(
            Method("icp", "ICP", lambda w, p, s: PointToLineIcp(w, p)), name, world, seeds
        )
        updates = len(_odd_base(name).scans) - 1
        lines += [
            f"**{name}** ({updates} updates per seed, map of {len(world.segments)} walls):",
            "",
            "| method | RMSE cm | median cm | p95 cm | max cm | over 0.5 m |",
            "| --- | ---: | ---: | ---: | ---: | ---: |",
            _row("RLuTF default on the built map", ours),
            *(_row(f"ICP point-to-line on the raw points, {k}", e) for k, e in icps.items()),
            _row("ICP point-to-line on the built map (bench settings)", poly),
            "",
        ]
        best_rmse = min(e.rmse for e in icps.values())
        best_median = min(e.percentile(50) for e in icps.values())
        ok = ours.rmse <= best_rmse and ours.percentile(50) <= best_median
        targets.append(
            f"| {name} | {_cm(ours.rmse)} vs {_cm(best_rmse)} | "
            f"{_cm(ours.percentile(50))} vs {_cm(best_median)} | {'yes' if ok else 'no'} |"
        )
    head = [
        "## Maps from logs that match the log: even scans build the map, odd scans are tracked",
        "",
        f"Command: `{_command(args)}`.",
        "",
        " ".join((__doc__ or "").split("\n\n")[2].split()),
        "",
        f"Odometry seeds {', '.join(map(str, seeds))}; errors pooled over them.",
        "",
        "Target: RLuTF's tracking RMSE and per-scan median at most the best of the ICP rows "
        "on the raw points.",
        "",
        "| log | RMSE cm, RLuTF vs best ICP | median cm | met |",
        "| --- | --- | --- | --- |",
        *targets,
        "",
    ]
    if args.variants:
        lines += _variants_table(logs, seeds, progress)
    return "\n".join(head + lines)


def _variants_table(
    logs: Sequence[str], seeds: Sequence[int], progress: Callable[[str], None]
) -> list[str]:
    head = "| variant | " + " | ".join(
        f"{n} RMSE | {n} median | {n} max | {n} from reference: RMSE / median" for n in logs
    )
    out = [
        "Variants, one change at a time (tracking errors in cm pooled over the seeds; "
        "*from reference*: each odd scan refined once from its corrected pose):",
        "",
        head + " |",
        "| --- |" + " ---: | ---: | ---: | ---: |" * len(logs),
    ]
    rows: list[str] = []
    progress("ICP from reference")
    wide = ICP_SETTINGS["gate 1 m, Huber 5 cm, 50 steps"]
    icp_ref = {n: icp_from_reference(n, wide) for n in logs}
    out.append(
        "| ICP on the raw points, gate 1 m (for comparison) | "
        + " | ".join(
            f"- | - | - | {_cm(icp_ref[n].rmse)} / {_cm(icp_ref[n].percentile(50))}" for n in logs
        )
        + " |"
    )
    for v in variants():
        cells = []
        for name in logs:
            progress(f"{name}: {v.label}")
            world = even_map(name, v.recipe)
            e = tracked(rlutf_method(v.config), name, world, seeds)
            ref = from_reference(name, world, v.config)
            cells.append(
                f"{_cm(e.rmse)} | {_cm(e.percentile(50))} | {_cm(float(e.errors.max()))} | "
                f"{_cm(ref.rmse)} / {_cm(ref.percentile(50))}"
            )
        rows.append(f"| {v.label} | " + " | ".join(cells) + " |")
    return out + rows + [""]


def _command(args: argparse.Namespace) -> str:
    parts = ["python -m bench.evenodd"]
    if args.logs != ",".join(LOGS):
        parts.append(f"--logs {args.logs}")
    if args.seeds != 3:
        parts.append(f"--seeds {args.seeds}")
    if not args.variants:
        parts.append("--no-variants")
    return " ".join([*parts, "--write"])


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.evenodd",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--logs", default=",".join(LOGS), help="comma-separated CARMEN logs")
    p.add_argument("--seeds", type=int, default=3, help="odometry seeds per log (default 3)")
    p.add_argument(
        "--no-variants", dest="variants", action="store_false", help="skip the variants table"
    )
    return section_main(p, lambda a: render(a, _stderr), SECTION, argv)


def _stderr(text: str) -> None:
    import sys

    print(text, file=sys.stderr, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
