"""Accuracy and speed benchmarks of RLuTF against the bound and the usual alternatives.

Run: ``python -m bench`` (full, about 25 minutes on two idle cores) or ``python -m bench
--quick`` (a smoke test under two minutes). Both rewrite the ``accuracy``, ``speed``,
``priors`` and ``relocalize`` sections of ``BENCHMARKS.md`` (``--output``; ``--no-write`` only
prints) and the figures in ``docs/bench/`` (``--plots``). ``python -m bench --write-logs DIR``
writes each scenario's first run as an MCAP input log with its ground truth (see
:mod:`bench.logs`) and exits.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from bench import plots as figures
from bench.accuracy import (
    FULL,
    QUICK,
    Profile,
    ScenarioResult,
    build_runs,
    run_accuracy,
    total_updates,
)
from bench.logs import write_run_files
from bench.methods import DEFAULT_METHOD, Method, table_methods
from bench.priors import priors_section
from bench.relocalize import relocalize_section
from bench.reloccases import FULL as RELOC_FULL
from bench.reloccases import QUICK as RELOC_QUICK
from bench.report import replace_section
from bench.speed import Point, growth, latency_vs_beams, latency_vs_map, speed_methods, sweep_maps
from bench.tables import overview_table, scenario_table, speed_tables, targets

ACCURACY = "accuracy"
SPEED = "speed"
PRIORS = "priors"
RELOCALIZE = "relocalize"


def machine() -> str:
    """One line naming the machine and the software."""
    import scipy

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next(
                (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu
            )
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}; "
        f"code {_revision()}; "
        f"CPython {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}; "
        "one process, one thread, methods run one after the other."
    )


def _revision() -> str:
    """The commit checked out, marked when the working tree has changes (read-only git)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{head} with local changes" if dirty else head


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        transient=False,
    )


def _command(argv: Sequence[str]) -> str:
    kept = [a for a in argv if a not in ("--no-write",)]
    return "python -m bench" + ("" if not kept else " " + " ".join(kept))


def accuracy_section(
    profile: Profile,
    methods: list[Method],
    plots: Path,
    rel: Path,
    only: Sequence[str] | None,
    command: str,
) -> tuple[str, list[ScenarioResult]]:
    """Run the accuracy benchmark; return its Markdown and the results."""

    results = build_runs(profile, only)
    with _progress() as bar:
        task = bar.add_task("accuracy", total=total_updates(results, methods))
        run_accuracy(results, methods, on_update=lambda: bar.advance(task))
    names = [m.name for m in methods]
    images = []
    for res in results:
        path = figures.trajectories(res, plots / f"trajectories-{res.name}.png")
        images.append(f"![{res.name}]({(rel / path.name).as_posix()})")
    err = figures.error_panels(results, names, plots / "errors.png")
    bars = figures.rmse_bars(results, names, plots / "rmse.png")
    log_figures = []
    for log in dict.fromkeys(r.runs[0].map_id for r in results if r.real):
        variants = [r for r in results if r.real and r.runs[0].map_id == log]
        fig = figures.log_errors(
            variants, names, plots / f"log-errors-{log}.png", f"{log}: position error per scan"
        )
        log_figures.append(f"![{log}: error over time]({(rel / fig.name).as_posix()})")
    ellipse_lines: list[str] = []
    shown = next(
        (
            r
            for r in results
            if not r.real and (t := r.traces.get(DEFAULT_METHOD)) and t[0].covariances is not None
        ),
        None,
    )
    if shown is not None:
        covs = shown.traces[DEFAULT_METHOD][0].covariances
        assert covs is not None
        scale = figures.ellipse_scale(covs)
        fig = figures.ellipses(shown, plots / f"ellipses-{shown.name}.png")
        size = (
            "at true size"
            if scale == 1.0
            else f"ellipse and error (estimate minus truth) both enlarged {scale:g} times to "
            "be seen, so the black dot (the true position) falls inside when the covariance "
            "covers the error"
        )
        ellipse_lines = [
            f"Covariance along a run ({shown.name}, seed {shown.runs[0].seed}): the true path, "
            f"the default's poses and every 10th update's 3-sigma position ellipse from its "
            f"covariance, {size}:",
            "",
            f"![covariance ellipses]({(rel / fig.name).as_posix()})",
            "",
        ]
    lines = [
        "## Accuracy against the bound and the alternatives",
        "",
        f"Command: `{command}` ({profile.name} profile: {profile.steps} scans per simulated run, "
        f"seeds {', '.join(map(str, profile.seeds))}; CARMEN logs "
        f"{'in full' if profile.carmen_limit is None else f'first {profile.carmen_limit} scans'})."
        " Every method gets the same runs: same scans, same odometry, same start pose.",
        "",
        f"Machine: {machine()}",
        "",
        "Methods: dead reckoning (odometry only); RLuTF `LocalizerConfig.paper()` (the paper read"
        " literally: turning functions), `LocalizerConfig.paper_area()` (the paper with the area "
        "between polygons), `LocalizerConfig(refine=False)` (the default without the "
        "least-squares refinement) and `LocalizerConfig()` (the default); point-to-line ICP "
        "against the map (`bench/baselines/icp.py`); an AMCL likelihood-field particle filter "
        "with Nav2's default parameters (`bench/baselines/amcl.py`: 500 to 2000 particles, "
        "alpha1..4 0.2, z_hit 0.5, z_rand 0.5, sigma_hit 0.2 m, 60 beams, updates after 0.25 m or"
        " 0.2 rad, KLD pf_err 0.05 pf_z 0.99; between filter updates its pose follows odometry, "
        "as AMCL's map->odom transform does). The bound is Censi's Cramer-Rao bound of each scan "
        "against the map at the true pose (`bench/crb.py`), RMS over the scans; divergence means "
        "an update over 0.5 m off; max error is the largest position error of any update; NEES is"
        " the mean over the updates of e^T P^-1 e, e = (dx, dy, wrap(dtheta)) the pose minus the "
        "truth and P the covariance the method returns (3 for a consistent covariance, chi-square"
        " with 3 dof); latency is one `update` call. The real logs are run twice: with the log's "
        "own odometry, and (`-odom5`) with odometry made from the SLAM poses' increments plus 5 %"
        " noise and a 0.02 rad/m heading bias.",
        "",
        "Translation RMSE, cm:",
        "",
        *overview_table(results, methods),
        "",
        f"![RMSE per scenario]({(rel / bars.name).as_posix()})",
        "",
        f"![Error over time]({(rel / err.name).as_posix()})",
        "",
    ]
    for res in results:
        lines += [*scenario_table(res, methods), ""]
    if log_figures:
        lines += [
            "Position error per scan on the real logs, every method, both odometry variants:",
            "",
            "\n\n".join(log_figures),
            "",
        ]
    lines += ellipse_lines
    lines += ["Trajectories of the first run of each scenario:", "", "\n\n".join(images)]
    return "\n".join(lines), results


def speed_section(
    profile: Profile, plots: Path, rel: Path, command: str
) -> tuple[str, list[Point], list[Point]]:
    """Run the speed sweeps; return their Markdown and the points by beams and by map."""

    methods = speed_methods()
    labels = {m.name: m.label for m in methods}
    n_maps = len(sweep_maps(profile))
    total = profile.speed_updates * len(methods) * (len(profile.speed_beams) + n_maps)
    with _progress() as bar:
        task = bar.add_task("speed", total=total)
        by_beams = latency_vs_beams(profile, methods, on_update=lambda: bar.advance(task))
        by_map = latency_vs_map(profile, methods, on_update=lambda: bar.advance(task))
    fits = growth(by_beams)
    fig1 = figures.latency(by_beams, plots / "latency-beams.png", "beams per scan", fits)
    fig2 = figures.latency(by_map, plots / "latency-map.png", "walls in the map (360 beams)")
    lines = [
        "## Speed: update latency against beams and map size",
        "",
        f"Command: `{command}` ({profile.name} profile: {profile.speed_updates} updates per "
        "point, nominal scenario, seed 1). AMCL here runs a filter update on every scan, with "
        "its default 60 beams and with every beam, so each method pays for the scan it gets.",
        "",
        f"Machine: {machine()}",
        "",
        *speed_tables(by_beams, by_map, fits, labels),
        "",
        f"![latency against beams]({(rel / fig1.name).as_posix()})",
        "",
        f"![latency against map size]({(rel / fig2.name).as_posix()})",
    ]
    return "\n".join(lines), by_beams, by_map


def write_logs(directory: Path, profile: Profile, only: Sequence[str] | None) -> None:
    """Write the first run of every scenario as an MCAP input log and ``.npz`` truth."""
    for res in build_runs(profile, only):
        path = write_run_files(res.runs[0], directory)
        print(f"{path} ({res.runs[0].updates} updates)")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    args_list = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small smoke-test profile")
    parser.add_argument("--output", type=Path, default=Path("BENCHMARKS.md"))
    parser.add_argument(
        "--plots",
        type=Path,
        default=None,
        help="figure directory (default: docs/bench beside --output)",
    )
    parser.add_argument(
        "--no-write",
        action="store_true",
        help="print only: leave --output alone (figures go to a temporary directory)",
    )
    parser.add_argument(
        "--only", choices=("accuracy", "speed", "priors", "relocalize"), help="run one part"
    )
    parser.add_argument("--scenarios", help="comma-separated scenario names (default: all)")
    parser.add_argument("--methods", help="comma-separated method names (default: all)")
    parser.add_argument(
        "--write-logs",
        type=Path,
        metavar="DIR",
        help="write the scenarios as MCAP input logs into DIR and exit",
    )
    args = parser.parse_args(args_list)
    profile = QUICK if args.quick else FULL
    only = args.scenarios.split(",") if args.scenarios else None
    if args.write_logs is not None:
        write_logs(args.write_logs, profile, only)
        return 0
    methods = table_methods(args.methods.split(",") if args.methods else None)
    if args.plots is not None:
        plots = args.plots
    elif args.no_write:
        plots = Path(tempfile.mkdtemp(prefix="bench-plots-"))
    else:
        plots = args.output.parent / "docs" / "bench"
    rel = Path(os.path.relpath(plots, args.output.parent))
    command = _command(args_list)
    started = time.perf_counter()
    sections: list[tuple[str, str]] = []
    results: list[ScenarioResult] = []
    by_beams: list[Point] = []
    by_map: list[Point] = []
    if args.only in (None, "accuracy"):
        text, results = accuracy_section(profile, methods, plots, rel, only, command)
        sections.append((ACCURACY, text))
    if args.only in (None, "speed"):
        text, by_beams, by_map = speed_section(profile, plots, rel, command)
        sections.append((SPEED, text))
    if args.only in (None, "priors"):
        with _progress() as bar:

            def progress(total: int):  # type: ignore[no-untyped-def]
                task = bar.add_task("priors", total=total)
                return lambda: bar.advance(task)

            text = priors_section(profile, command, machine(), progress)
        sections.append((PRIORS, text))
    if args.only in (None, "relocalize"):
        with _progress() as bar:

            def reloc_progress(total: int):  # type: ignore[no-untyped-def]
                task = bar.add_task("relocalize", total=total)
                return lambda: bar.advance(task)

            text = relocalize_section(
                RELOC_QUICK if args.quick else RELOC_FULL,
                plots,
                rel,
                command,
                machine(),
                reloc_progress,
            )
        sections.append((RELOCALIZE, text))
    if results:
        rows = targets(results, by_beams, by_map)
        check = "\n".join(
            [
                "",
                "Issue targets for the default localizer (speed rows from the speed section of "
                "this run):",
                "",
                *rows,
            ]
        )
        sections[0] = (
            ACCURACY,
            sections[0][1].replace(
                "\nTranslation RMSE, cm:", check + "\n\nTranslation RMSE, cm:", 1
            ),
        )
    for name, text in sections:
        print(text, "\n")
        if not args.no_write:
            replace_section(args.output, name, text)
    print(f"done in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
