"""Maps from logs that match the log: the even scans build the map, the odd scans are tracked.

Run: ``python -m bench.evenodd [--logs intel,aces] [--seeds 3] [--no-variants] [--write]``
(one of ``--neighbours``, ``--coarse-to-fine``, ``--fitted-walls``, ``--settle``, ``--worst``,
``--cost`` instead: that section only).

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
import platform
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from bench.baselines.icp import PointToLineIcp
from bench.carmen import ODOM5_SEED
from bench.evenodd_runs import (
    ICP_SETTINGS,
    LOGS,
    Errors,
    MapRecipe,
    answer_on_method,
    coarse_to_fine_method,
    even_map,
    from_reference,
    hit_to_wall,
    icp_from_reference,
    icp_method,
    leave_out_method,
    odd_base,
    odd_run,
    raw_answer_method,
    rlutf_method,
    tracked,
    update_seconds,
    variants,
)
from bench.evenodd_settle import render_settle
from bench.evenodd_worst import render_worst
from bench.methods import Method
from bench.report import replace_section
from bench.wallfit import WallFit
from rlutf.localizer import LocalizerConfig
from rlutf.map import coarse_map

SECTION = "evenodd"
#: The section of ``--neighbours``.
NEIGHBOURS_SECTION = "evenodd-neighbours"
#: The section of ``--coarse-to-fine``.
COARSE_SECTION = "evenodd-coarse"
#: The section of ``--cost``.
COST_SECTION = "evenodd-cost"
#: The section of ``--fitted-walls``.
FITTED_SECTION = "evenodd-fitted"
#: The section of ``--settle``.
SETTLE_SECTION = "evenodd-settle"
#: The section of ``--worst``.
WORST_SECTION = "evenodd-worst"
#: ICP settings of the ``--neighbours`` table (the best of :data:`ICP_SETTINGS` on both logs).
NEIGHBOURS_ICP = "gate 2 m to 0.2 m, 50 steps"


def _markdown(text: str) -> str:
    """reStructuredText roles and literals as Markdown code."""
    return re.sub(r":\w+:`~?", "`", text).replace("``", "`")


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
        updates = len(odd_base(name).scans) - 1
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
        _markdown(" ".join((__doc__ or "").split("\n\n")[2].split())),
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


def render_neighbours(
    args: argparse.Namespace, progress: Callable[[str], None] = lambda s: None
) -> str:
    """ICP on the raw points with the even scans around each tracked scan left out."""
    logs = [s for s in args.logs.split(",") if s]
    seeds = [ODOM5_SEED + i for i in range(args.seeds)]
    cfg = ICP_SETTINGS[NEIGHBOURS_ICP]
    lines = [
        "### Where ICP's lead on the raw points comes from: the scans next to the tracked one",
        "",
        f"Command: `{_command(args)}`.",
        "",
        "The same runs as above; ICP on the raw points (settings: "
        f"{NEIGHBOURS_ICP}) with the even scans around each tracked odd scan left out of its "
        "map: window 1 leaves out the even scan just before and the one just after (taken "
        "a moment apart from nearly the same place, with the people standing where they stood, "
        "and at corrected poses that the log's SLAM found by matching these very scans); "
        "window 5, the five before and after. *From reference*: each odd scan aligned "
        f"once from its corrected pose. Odometry seeds {', '.join(map(str, seeds))}.",
        "",
        "| log | method | RMSE cm | median cm | p95 cm | max cm | over 0.5 m | "
        "from reference: RMSE / median cm |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    default = LocalizerConfig()
    for name in logs:
        world = even_map(name)
        progress(f"{name}: RLuTF default")
        ours = tracked(rlutf_method(default), name, world, seeds)
        ref = from_reference(name, world, default)
        lines.append(
            f"| {name} | {_row('RLuTF default on the built map', ours)[2:]} "
            f"{_cm(ref.rmse)} / {_cm(ref.percentile(50))} |"
        )
        for window in (0, 1, 5):
            progress(f"{name}: ICP, window {window}")
            if window == 0:
                method = icp_method(name, cfg)
                label = "ICP on the raw points of every even scan"
            else:
                method = leave_out_method(name, cfg, window)
                label = f"ICP on the raw points, window {window} left out"
            e = tracked(method, name, world, seeds)
            r = icp_from_reference(name, cfg, window)
            lines.append(
                f"| {name} | {_row(label, e)[2:]} {_cm(r.rmse)} / {_cm(r.percentile(50))} |"
            )
    return "\n".join([*lines, ""])


def render_coarse(
    args: argparse.Namespace, progress: Callable[[str], None] = lambda s: None
) -> str:
    """The coarse-to-fine trial against the default and ICP's best setting."""
    logs = [s for s in args.logs.split(",") if s]
    seeds = [ODOM5_SEED + i for i in range(args.seeds)]
    lines = [
        "### A trial: track on walls simplified at one cell, refine on the map as built",
        "",
        f"Command: `{_command(args)}`.",
        "",
        "The same runs as above. *Coarse to fine*, the trial that led to the localizer's "
        "`coarse_tolerance`: `LocalizerConfig(coarse_tolerance=0)` tracks on the map "
        "simplified at 1 cell (5 cm) when it is built and each of its poses is refined on the "
        "map as built (`bench.evenodd_runs.CoarseToFine`). *RLuTF default* is the localizer "
        "of 0.4, which tracks on the map's walls simplified at 7 cm by itself; *RLuTF before "
        "0.4* is `coarse_tolerance=0`. "
        f"Odometry seeds {', '.join(map(str, seeds))}.",
        "",
        "| log | method | RMSE cm | median cm | p95 cm | max cm | over 0.5 m |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name in logs:
        world = even_map(name)
        progress(f"{name}: RLuTF default")
        ours = tracked(rlutf_method(LocalizerConfig()), name, world, seeds)
        progress(f"{name}: RLuTF before 0.4")
        before = tracked(rlutf_method(LocalizerConfig(coarse_tolerance=0.0)), name, world, seeds)
        progress(f"{name}: coarse to fine")
        c2f = tracked(coarse_to_fine_method(name, MapRecipe(simplify=0.05)), name, world, seeds)
        progress(f"{name}: ICP")
        icp = tracked(icp_method(name, ICP_SETTINGS[NEIGHBOURS_ICP]), name, world, seeds)
        lines += [
            f"| {name} | {_row('RLuTF default', ours)[2:]}",
            f"| {name} | {_row('RLuTF before 0.4 (`coarse_tolerance=0`)', before)[2:]}",
            f"| {name} | {_row('RLuTF coarse to fine (trial)', c2f)[2:]}",
            f"| {name} | {_row(f'ICP on the raw points, {NEIGHBOURS_ICP}', icp)[2:]}",
        ]
    return "\n".join([*lines, ""])


def render_fitted(
    args: argparse.Namespace, progress: Callable[[str], None] = lambda s: None
) -> str:
    """The trial of walls moved onto the hit points (:mod:`bench.wallfit`)."""
    logs = [s for s in args.logs.split(",") if s]
    seeds = [ODOM5_SEED + i for i in range(args.seeds)]
    config = LocalizerConfig()
    recipes = {
        "fitted walls: the cell edges traced, moved onto the hits, simplified at 0.25 cell": (
            MapRecipe(simplify=0.0, fit=WallFit())
        ),
        "fitted walls: the map as built (simplified at half a cell) moved onto the hits": (
            MapRecipe(fit=WallFit(simplify=0.0))
        ),
    }
    lines = [
        "### A trial: walls moved onto the hit points",
        "",
        f"Command: `{_command(args)}`.",
        "",
        "The same runs as above. *Fitted walls*: the map `rlutf map build` traces (surface "
        "offset 0.4 cell), its vertices then moved so that the walls pass through the even "
        "scans' hit points (those in cells that are not free), by the regularised "
        "least-squares fit of `bench.wallfit.fit_walls` (`bench.wallfit.WallFit` defaults: "
        "hits within 5 cm of a wall whose free side faces the scanner, Huber 1.5 cm, "
        "displacements held to each other along the ring, at most 5 cm). *Answer on fitted "
        "walls*: the default localizer tracks on the map as built, and each of its poses is "
        "refined on the fitted walls of the first row (`bench.evenodd_runs.CoarseToFine`). "
        "*Answer by ICP on the raw points*: the default localizer tracks on the map as built, "
        "and each of its poses is aligned by ICP on the raw points (gate 2 m to 0.2 m, 50 "
        "steps), the aligned pose fed back (`bench.evenodd_runs.RawAnswer`: a trial of keeping "
        "the log's points beside the walls for the answer). "
        "*From reference*: each odd scan refined once from its corrected pose. *Hit to wall*: "
        "median distance from the even scans' hits in cells that are not free to the nearest "
        "wall. "
        f"Odometry seeds {', '.join(map(str, seeds))}.",
        "",
        "| log | map | walls | hit to wall cm | RMSE cm | median cm | p95 cm | max cm | "
        "over 0.5 m | from reference: RMSE / median cm |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name in logs:
        worlds = {"as `rlutf map build` writes it": even_map(name)}
        worlds.update({label: even_map(name, r) for label, r in recipes.items()})
        for label, world in worlds.items():
            progress(f"{name}: {label}")
            e = tracked(rlutf_method(config), name, world, seeds)
            ref = from_reference(name, world, config)
            cells = f"{label} | {len(world.segments)} | {hit_to_wall(name, world):.2f}"
            lines.append(f"| {name} {_row(cells, e)} {_cm(ref.rmse)} / {_cm(ref.percentile(50))} |")
        fitted = even_map(name, next(iter(recipes.values())))
        progress(f"{name}: answer on fitted walls")
        answer = tracked(answer_on_method(name), name, fitted, seeds)
        label = f"answer on fitted walls | {len(fitted.segments)} | -"
        lines.append(f"| {name} {_row(label, answer)} - |")
        built = even_map(name)
        progress(f"{name}: answer by ICP on the raw points")
        raw = tracked(raw_answer_method(name), name, built, seeds)
        label = f"answer by ICP on the raw points | {len(built.segments)} | -"
        lines.append(f"| {name} {_row(label, raw)} - |")
    return "\n".join([*lines, ""])


def render_cost(args: argparse.Namespace, progress: Callable[[str], None] = lambda s: None) -> str:
    """Time per update of the localizer on the built maps, with and without the coarse map."""
    logs = [s for s in args.logs.split(",") if s]
    configs = {
        "`LocalizerConfig()` (0.4: simplified walls, answer on the map)": LocalizerConfig(),
        "`coarse_tolerance=0` (tracked on the map, as before 0.4)": LocalizerConfig(
            coarse_tolerance=0.0
        ),
    }
    lines = [
        "### Cost per update on the built maps",
        "",
        f"Command: `{_command(args)}` (no other timing run at the same time; machine: "
        f"{platform.machine()}, CPython {platform.python_version()}, one process).",
        "",
        f"Each odd scan of odometry seed {ODOM5_SEED} tracked once per setting, the settings "
        "taking turns over three passes; wall-clock time of `Localizer.update` "
        "(`time.perf_counter`), pooled over the passes.",
        "",
        "| log | localizer | updates | median ms | p90 ms | mean ms |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for name in logs:
        world = even_map(name)
        run = odd_run(name, world)
        coarse_map(world, LocalizerConfig().coarse_tolerance)
        times: dict[str, list[float]] = {label: [] for label in configs}
        for turn in range(3):
            for label, config in configs.items():
                progress(f"{name}: {label}, pass {turn + 1}")
                times[label] += update_seconds(config, run)
        for label, t in times.items():
            ms = 1e3 * np.asarray(t)
            lines.append(
                f"| {name} | {label} | {len(ms)} | {np.median(ms):.2f} | "
                f"{np.percentile(ms, 90):.2f} | {ms.mean():.2f} |"
            )
    return "\n".join([*lines, ""])


def _command(args: argparse.Namespace) -> str:
    parts = ["python -m bench.evenodd"]
    if args.logs != ",".join(LOGS):
        parts.append(f"--logs {args.logs}")
    if args.seeds != 3:
        parts.append(f"--seeds {args.seeds}")
    if args.neighbours:
        parts.append("--neighbours")
    elif args.cost:
        parts.append("--cost")
    elif args.coarse:
        parts.append("--coarse-to-fine")
    elif args.fitted:
        parts.append("--fitted-walls")
    elif args.settle:
        parts.append("--settle")
    elif args.worst:
        parts.append("--worst")
    elif not args.variants:
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
    p.add_argument(
        "--neighbours",
        action="store_true",
        help="only the table of ICP with the neighbouring even scans left out (its own section)",
    )
    p.add_argument(
        "--coarse-to-fine",
        dest="coarse",
        action="store_true",
        help="only the coarse-to-fine trial (its own section)",
    )
    p.add_argument(
        "--fitted-walls",
        dest="fitted",
        action="store_true",
        help="only the trial of walls moved onto the hit points (its own section)",
    )
    p.add_argument(
        "--settle",
        action="store_true",
        help="only where each refinement settles from a start a few centimetres off, apart "
        "from tracking (its own section)",
    )
    p.add_argument(
        "--worst",
        action="store_true",
        help="only the scans where RLuTF trails ICP the most, with what the map says about each "
        "(its own section)",
    )
    p.add_argument(
        "--cost",
        action="store_true",
        help="only the time per update, with and without the coarse map (its own section; run "
        "it when no other timing runs)",
    )
    p.add_argument("--write", action="store_true", help="update BENCHMARKS.md")
    args = p.parse_args(argv)
    if args.neighbours:
        text, section = render_neighbours(args, _stderr), NEIGHBOURS_SECTION
    elif args.cost:
        text, section = render_cost(args, _stderr), COST_SECTION
    elif args.coarse:
        text, section = render_coarse(args, _stderr), COARSE_SECTION
    elif args.fitted:
        text, section = render_fitted(args, _stderr), FITTED_SECTION
    elif args.settle:
        logs = [s for s in args.logs.split(",") if s]
        text, section = render_settle(logs, _command(args), _stderr), SETTLE_SECTION
    elif args.worst:
        logs, seeds = args.logs.split(","), [ODOM5_SEED + i for i in range(args.seeds)]
        text, section = render_worst(logs, seeds, _command(args), _stderr), WORST_SECTION
    else:
        text, section = render(args, _stderr), SECTION
    print(text)
    if args.write:
        replace_section(Path("BENCHMARKS.md"), section, text)
    return 0


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
