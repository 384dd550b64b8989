"""The service's CPU per scan against the localizer's update time: how much is not localization.

Run: ``python -m bench.costfit [--robots 100] [--beams 90,180,360,720] [--duration 20]
[--write]``.

Issue 21 asks for the fit of the service's CPU per scan against the localizer's update time.
The beams per scan change what an update costs and little else (one scan, one pose, two odometry
readings a scan whatever its beams), so for each beam count this measures, one after the other
and never at the same time:

- the localizer alone: CPU ms per ``Localizer.update`` on decoded scans, one process, 20
  simulated robots (:func:`bench.floor.localizer_ms`);
- the service: ``rlutf serve`` (its default layout, recording on) against the load generator of
  :mod:`bench.fleet`, the same number of robots at every beam count; CPU ms of all its processes
  per pose published.

A least-squares line through the points, ``service = fixed + slope x update``, splits a scan's
cost into the part that grows with the localizer's work and the part that does not (``fixed``:
the bus, decoding, recording, bookkeeping). Two readings of "not localization" at each beam
count follow: the fixed part's share of the service's CPU, and everything beyond the localizer's
own update (``1 - update / service``: the fixed part and what the service's setting adds to the
update itself, other processes on the same cores included).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
from dataclasses import dataclass

import numpy as np

from bench.fleetrun import RATE_HZ, WARMUP_STEPS, run_size, serve_layout
from bench.floor import localizer_alone_ms
from bench.report import positive_float, positive_ints, section_main

#: The section of ``BENCHMARKS.md``, one per fleet size: ``costfit-{robots}``.
SECTION = "costfit"
#: Robots and steps of the plan the localizer alone is timed on (as ``python -m bench.floor``).
ALONE_ROBOTS = 20
ALONE_STEPS = 300


@dataclass(frozen=True)
class Point:
    """One beam count's measurements.

    Attributes:
        beams: beams a scan.
        update_ms: CPU ms per ``Localizer.update``, the localizer alone.
        service_ms: the service's CPU ms (all its processes) per pose published.
        sent_ms: the same per scan sent.
        answered: share of the scans sent after each robot's first 2 s that were answered.
        p99_ms: their scan-to-pose latency's 99th percentile.
    """

    beams: int
    update_ms: float
    service_ms: float
    sent_ms: float
    answered: float
    p99_ms: float


def fit_line(xs: list[float], ys: list[float]) -> tuple[float, float]:
    """``(intercept, slope)`` of the least-squares line ``y = intercept + slope x``.

    Raises:
        ValueError: fewer than two points, or every ``x`` the same.
    """
    if len(xs) != len(ys) or len(set(xs)) < 2:
        raise ValueError(f"a line needs two different x or more, got {xs}")
    slope, intercept = np.polyfit(np.asarray(xs), np.asarray(ys), 1)
    return float(intercept), float(slope)


def shares(point: Point, fixed: float) -> tuple[float, float]:
    """At one point: the fixed part's share of the service's CPU per pose, and the share beyond
    the localizer's own update."""
    return fixed / point.service_ms, 1.0 - point.update_ms / point.service_ms


def median_point(runs: list[Point]) -> Point:
    """One beam count's runs as one point: the median of each measurement."""
    beams = {p.beams for p in runs}
    if len(beams) != 1:
        raise ValueError(f"runs of different beam counts: {sorted(beams)}")

    def mid(values: list[float]) -> float:
        return float(statistics.median(values))

    return Point(
        runs[0].beams,
        mid([p.update_ms for p in runs]),
        mid([p.service_ms for p in runs]),
        mid([p.sent_ms for p in runs]),
        mid([p.answered for p in runs]),
        mid([p.p99_ms for p in runs]),
    )


def measure(beams: list[int], robots: int, duration: float, rounds: int = 1) -> list[Point]:
    """Each round, every beam count's localizer alone first, then the service at each, one at a
    time; each point the median of its rounds."""
    workers, processes = serve_layout(None, None)
    serve = ("--processes", str(processes)) if processes else ()
    runs: dict[int, list[Point]] = {b: [] for b in beams}
    for k in range(rounds):
        alone = {b: localizer_alone_ms(b, ALONE_ROBOTS, ALONE_STEPS) for b in beams}
        for b in beams:
            r = run_size(robots, duration, True, workers, serve_flags=serve, beams=b)
            runs[b].append(
                Point(
                    b,
                    alone[b],
                    r["cpu_service_per_pose"],
                    r["cpu_main"] + r["cpu_workers"],
                    r["answered_after"],
                    r["p99"],
                )
            )
            print(f"round {k + 1}, {b} beams: {runs[b][-1]}", flush=True)
    return [median_point(runs[b]) for b in beams]


def report(points: list[Point], robots: int, duration: float, load: float, rounds: int = 1) -> str:
    """The Markdown section for measured ``points`` (each the median of ``rounds`` runs)."""
    fixed, slope = fit_line([p.update_ms for p in points], [p.service_ms for p in points])
    beams = ",".join(str(p.beams) for p in points)
    rows = []
    for p in points:
        fixed_share, beyond = shares(p, fixed)
        rows.append(
            f"| {p.beams} | {p.update_ms:.3f} | {p.service_ms:.3f} | {p.sent_ms:.3f} "
            f"| {100.0 * p.answered:.1f} | {p.p99_ms:.1f} "
            f"| {fixed + slope * p.update_ms:.3f} | {100.0 * fixed_share:.0f} % "
            f"| {100.0 * beyond:.0f} % |"
        )
    return "\n".join(
        [
            f"Command: `python -m bench.costfit --robots {robots} --beams {beams} "
            f"--duration {duration:g}{f' --rounds {rounds}' if rounds > 1 else ''} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}. *Update*: CPU ms per `Localizer.update`, the localizer "
            f"alone in one process ({ALONE_ROBOTS} simulated robots, {ALONE_STEPS} steps each, "
            "`bench.floor.localizer_ms`), every beam count timed before the first service of "
            "the round started. *Service*: `rlutf serve` (its default layout, recording on) and "
            f"the load generator of `python -m bench.fleet` on the same cores, {robots} robots "
            f"at 10 Hz, {duration:g} s per beam count; CPU ms of all the service's processes "
            "per pose published and per scan sent; answered and p99 over the scans after each "
            f"robot's first {WARMUP_STEPS / RATE_HZ:g} s."
            + (
                f" {rounds} rounds, the beam counts in turn in each (the localizer alone first); "
                "each figure the median of its rounds."
                if rounds > 1
                else ""
            )
            + f" Load average when the run started: {load:.1f}.",
            "",
            "| beams | update ms | service ms per pose | per scan sent | answered % | p99 ms "
            "| the line at this update | fixed part's share | beyond the update alone |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            *rows,
            "",
            f"Least-squares line, service CPU per pose against the update: **{fixed:.3f} ms + "
            f"{slope:.2f} x the update**. The fixed part is what a scan costs the service "
            "whatever its localization; a slope over 1 is the update costing more inside the "
            "service than alone (the cores shared with the other processes and threads). "
            "Issue 21's goal is under a third not localization.",
        ]
    )


def one_or_more(text: str) -> int:
    """An argparse type: one whole number, at least 1 (robots, rounds)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give one whole number of 1 or more, e.g. 3")
    return n


def beam_counts(text: str) -> list[int]:
    """An argparse type: beams a scan, two different counts or more."""
    counts = positive_ints(text)
    if len(set(counts)) < 2:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give two different beam counts or more (the fit is a line), e.g. 90,360"
        )
    return counts


def render(args: argparse.Namespace) -> str:
    load = os.getloadavg()[0]
    points = measure(args.beams, args.robots, args.duration, args.rounds)
    return report(points, args.robots, args.duration, load, args.rounds)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.costfit",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=one_or_more, default=100, help="robots at every beam count")
    p.add_argument(
        "--beams",
        type=beam_counts,
        default="90,180,360,720",
        help="beams a scan, comma-separated: two different counts or more (a line needs them)",
    )
    p.add_argument("--duration", type=positive_float, default=20.0, help="seconds per beam count")
    p.add_argument(
        "--rounds",
        type=one_or_more,
        default=1,
        help="runs of every beam count, the counts in turn (each figure the median)",
    )
    return section_main(p, render, lambda a: f"{SECTION}-{a.robots}", argv)


if __name__ == "__main__":
    raise SystemExit(main())
