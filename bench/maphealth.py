"""Issue 23: map health on buildings whose world differs from the map, and on a real log.

Run: ``python -m bench.maphealth [--seeds 1,2,3] [--robots 4] [--seconds 90] [--png FILE]
[--write]``.

Each case is a procedural building (:func:`rlutf.sim.make_building`); the map is the building
as drawn, the world the robots drive in differs from it: two racks (1.2 m x 0.5 m) stand in
the open, one doorway is blocked by a panel, and 1.5 m of an interior wall is gone. Eight
people walk about (not on the map either). ``--robots`` robots drive their own paths for
``--seconds`` at 10 Hz with drifting odometry, each tracked by a default :class:`Localizer` on
the map; every scan at a pose that is not lost, scores at least 0.8 and whose range is under
0.1 m is counted into one :class:`rlutf.mapchange.ChangeGrid`, as the service does. A control
case has the same building with nothing changed and the people walking: nothing may be
reported.

Graded against the truth: an added rack or panel is found when an ``added`` region lies within
0.3 m of it, the removed wall when a ``removed`` line does; false reports are the area of
``added`` regions and the length of ``removed`` lines farther than 0.3 m from every true change.
The time to report is when the change first appears in the report (reports made every 5 s of
the run), with the robot passes until then (a pass: a robot within 5 m of the change, counted
once per robot per 10 s). Cost: CPU time (``time.process_time``) of the evidence and of
counting it per scan, beside the update's own.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon, box
from shapely.geometry.base import BaseGeometry

from bench.report import ints_text, section_main
from rlutf.localizer import Localizer
from rlutf.map import Map
from rlutf.mapchange import Change, ChangeGrid, find_changes
from rlutf.motion import relative
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    people_walk,
    random_free_point,
    simulate_scan,
)

SECTION = "maphealth"
NEAR = 0.3
GOOD_SCORE = 0.8
GOOD_RANGE = 0.1
DT = 0.1


@dataclass
class Truth:
    """What differs between the world and the map."""

    added: list[Polygon] = field(default_factory=list)
    removed: list[BaseGeometry] = field(default_factory=list)
    names: list[str] = field(default_factory=list)


def _door(world: Map) -> Polygon | None:
    """A doorway of the building: two wall ends (0.15 m edges) facing each other 1 m apart."""
    segs = world.segments
    length = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    ends = segs[np.abs(length - 0.15) < 1e-3]
    mids = 0.5 * (ends[:, :2] + ends[:, 2:])
    for i in range(len(ends)):
        for j in range(i + 1, len(ends)):
            if abs(math.dist(mids[i], mids[j]) - 1.0) < 1e-3:
                hull = shapely.MultiPoint([*ends[i].reshape(2, 2), *ends[j].reshape(2, 2)])
                return shapely.convex_hull(hull)
    return None


def _thin_wall(world: Map, rng: np.random.Generator) -> tuple[Polygon, BaseGeometry] | None:
    """1.5 m of an interior wall (free space on both sides): the region to open, and the map's
    wall lines there."""
    segs = world.segments
    length = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    for k in rng.permutation(np.flatnonzero(length > 2.5)):
        a, b = segs[k, :2], segs[k, 2:]
        u = (b - a) / length[k]
        n = np.array([-u[1], u[0]])  # free space on the left
        mid = a + u * rng.uniform(1.0, length[k] - 1.0)
        behind = mid - n * 0.4
        if not world.contains_point(float(behind[0]), float(behind[1])):
            continue
        corners = [
            mid + u * 0.75 * s + n * t for s, t in ((-1, 0.05), (1, 0.05), (1, -0.3), (-1, -0.3))
        ]
        region = Polygon(corners)
        lines = world.geometry.boundary.intersection(region)
        if lines.length < 2.9:
            continue
        return region, lines
    return None


def changed_world(world: Map, seed: int) -> tuple[Map, Truth]:
    """The world as it is: racks added, a doorway blocked, a wall segment gone."""
    rng = np.random.default_rng([seed, 11])
    free = world.geometry
    truth = Truth()
    for i in range(2):
        for _ in range(200):
            p = random_free_point(world, rng, 1.4)
            rack = box(p[0] - 0.6, p[1] - 0.25, p[0] + 0.6, p[1] + 0.25)
            if rng.random() < 0.5:
                rack = box(p[0] - 0.25, p[1] - 0.6, p[0] + 0.25, p[1] + 0.6)
            if all(rack.distance(r) > 2.0 for r in truth.added):
                truth.added.append(rack)
                truth.names.append(f"rack {i + 1}")
                break
    door = _door(world)
    if door is not None:
        panel = door.buffer(-0.01)
        truth.added.append(panel)
        truth.names.append("doorway blocked")
    free = free.difference(shapely.union_all(truth.added))
    wall = _thin_wall(world, rng)
    if wall is not None:
        region, lines = wall
        free = free.union(region.intersection(box(*world.bounds)))
        truth.removed.append(lines)
        truth.names.append("wall removed")
    if not isinstance(free, Polygon):
        free = max(free.geoms, key=lambda g: g.area)
    return Map.from_shapely(shapely.set_precision(free, 1e-6)), truth


@dataclass
class Outcome:
    """One case's grading."""

    name: str
    # (change, seconds until reported, passes until then (None: not reported), passes in all)
    found: list[tuple[str, float | None, int | None, int]]
    false_area: float
    false_length: float
    reported: list[Change]
    scans: int
    counted: int
    update_cpu: float
    health_cpu: float
    report_cpu: float  # median CPU seconds of one report
    world: Map
    truth: Truth


def _false(changes: Sequence[Change], truth: Truth) -> tuple[float, float]:
    real = [*truth.added, *truth.removed]
    area = length = 0.0
    for c in changes:
        near = any(c.geometry.distance(t) <= NEAR for t in real)
        if near:
            continue
        if c.kind == "added":
            area += c.geometry.area
        else:
            length += c.geometry.length
    return area, length


def _matches(changes: Sequence[Change], kind: str, target: BaseGeometry) -> bool:
    return any(c.kind == kind and c.geometry.distance(target) <= NEAR for c in changes)


def run_case(
    seed: int, robots: int, seconds: float, change: bool = True, people: int = 8
) -> Outcome:
    """One building, ``robots`` robots for ``seconds``, with or without the changes."""
    mrng = np.random.default_rng(seed)
    world = make_building(mrng, 24.0, 14.0, 3, 2)
    real, truth = changed_world(world, seed) if change else (world, Truth())
    steps = round(seconds / DT) + 1
    lidar = LidarModel()
    crowd = np.stack(list(people_walk(real, np.random.default_rng([seed, 4]), people, steps, DT)))
    grid = ChangeGrid(world)
    targets = [("added", g) for g in truth.added] + [("removed", g) for g in truth.removed]
    first: list[tuple[float, int] | None] = [None] * len(targets)
    passes = [0] * len(targets)
    last_pass: dict[tuple[int, int], float] = {}
    paths, odos, locs, rngs = [], [], [], []
    for r in range(robots):
        truth_path = make_trajectory(real, np.random.default_rng([seed, 20 + r]), steps, dt=DT)
        paths.append(truth_path)
        odos.append(
            drift_odometry(truth_path, OdometryModel(), np.random.default_rng([seed, 40 + r]))
        )
        locs.append(Localizer(world, truth_path[0], seed=r))
        rngs.append(np.random.default_rng([seed, 60 + r]))
    update_cpu = health_cpu = 0.0
    report_cpu: list[float] = []
    scans = counted = 0
    stamp0 = 1_700_000_000_000_000_000
    for k in range(1, steps):
        stamp = stamp0 + round(k * DT * 1e9)
        for r in range(robots):
            scan = simulate_scan(real, paths[r][k], lidar, rngs[r], people=crowd[k])
            c0 = time.process_time()
            res = locs[r].update(relative(odos[r][k - 1], odos[r][k]), scan)
            c1 = time.process_time()
            scans += 1
            if (
                res.status != "lost"
                and res.score >= GOOD_SCORE
                and res.deviation_range <= GOOD_RANGE
                and res.returns is not None
            ):
                grid.add(res.returns, stamp, f"r{r}")
                counted += 1
            health_cpu += time.process_time() - c1
            update_cpu += c1 - c0
            if k == 1:  # the kernels' first call compiles or loads them: not a scan's cost
                update_cpu = health_cpu = 0.0
            t = k * DT
            for i, (_, g) in enumerate(targets):
                if g.distance(shapely.Point(paths[r][k][:2])) < 5.0:
                    if t - last_pass.get((i, r), -math.inf) > 10.0:
                        passes[i] += 1
                    last_pass[(i, r)] = t
        if k % round(5.0 / DT) == 0:
            c0 = time.process_time()
            changes = find_changes(grid)
            report_cpu.append(time.process_time() - c0)
            for i, (kind, g) in enumerate(targets):
                if first[i] is None and _matches(changes, kind, g):
                    first[i] = (k * DT, passes[i])
    changes = find_changes(grid)
    found = []
    for i, (kind, g) in enumerate(targets):
        ok = _matches(changes, kind, g)
        at = first[i]
        found.append(
            (truth.names[i], at[0] if ok and at else None, at[1] if ok and at else None, passes[i])
        )
    area, length = _false(changes, truth)
    return Outcome(
        f"building {seed}" + ("" if change else " (nothing changed)"),
        found,
        area,
        length,
        changes,
        scans,
        counted,
        update_cpu,
        health_cpu,
        float(np.median(report_cpu)) if report_cpu else math.nan,
        world,
        truth,
    )


def real_case(name: str) -> Outcome | None:
    """A real log whose map was built from the log itself: nothing changed, nothing may be
    reported (``None`` when the log is not there)."""
    from bench.accuracy import has_data
    from bench.carmen import carmen_run

    if not has_data(name):
        return None
    run = carmen_run(name)
    grid = ChangeGrid(run.world)
    loc = Localizer(run.world, run.truth[0], seed=1)
    update_cpu = health_cpu = 0.0
    counted = 0
    report_cpu: list[float] = []
    for k in range(1, len(run.scans)):
        c0 = time.process_time()
        res = loc.update(relative(run.odometry[k - 1], run.odometry[k]), run.scans[k])
        c1 = time.process_time()
        if _good(res):
            assert res.returns is not None
            grid.add(res.returns, int(run.stamps_ns[k]), name)
            counted += 1
        c2 = time.process_time()
        if k > 1:
            update_cpu += c1 - c0
            health_cpu += c2 - c1
        if k % 50 == 0:
            report_cpu.append(_timed_report(grid)[1])
    changes = find_changes(grid)
    area, length = _false(changes, Truth())
    return Outcome(
        f"{name} (real log, map built from it)", [], area, length, changes, len(run.scans) - 1,
        counted, update_cpu, health_cpu, float(np.median(report_cpu)), run.world, Truth(),
    )  # fmt: skip


def _good(res: object) -> bool:
    """Whether a pose is trusted enough to count its scan (as the service does)."""
    return (
        getattr(res, "status", "lost") != "lost"
        and getattr(res, "score", 0.0) >= GOOD_SCORE
        and getattr(res, "deviation_range", math.inf) <= GOOD_RANGE
        and getattr(res, "returns", None) is not None
    )


def _timed_report(grid: ChangeGrid) -> tuple[list[Change], float]:
    c0 = time.process_time()
    changes = find_changes(grid)
    return changes, time.process_time() - c0


def draw(outcome: Outcome, path: Path) -> Path:
    """The map, the true changes and the report."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5))
    for poly in getattr(outcome.world.geometry, "geoms", [outcome.world.geometry]):
        for ring in (poly.exterior, *poly.interiors):
            x, y = ring.xy
            ax.plot(x, y, color="black", lw=1.0)
    for g in outcome.truth.added:
        x, y = g.exterior.xy
        ax.fill(x, y, color="tab:orange", alpha=0.35, lw=0, label="true: added")
    for g in outcome.truth.removed:
        for line in getattr(g, "geoms", [g]):
            x, y = line.xy
            ax.plot(x, y, color="tab:orange", lw=6, alpha=0.5, label="true: removed")
    for c in outcome.reported:
        for part in getattr(c.geometry, "geoms", [c.geometry]):
            if isinstance(part, Polygon):
                x, y = part.exterior.xy
                ax.plot(x, y, color="tab:red", lw=1.5, label="reported: added")
            elif isinstance(part, LineString):
                x, y = part.xy
                ax.plot(x, y, color="tab:blue", lw=2.5, label="reported: removed")
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_title(f"Map health, {outcome.name}: the map (black), the world's changes, the report")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def render(
    seeds: Sequence[int], robots: int, seconds: float, png: Path | None, command: str
) -> str:
    """The section of ``BENCHMARKS.md``."""
    outcomes = [run_case(s, robots, seconds) for s in seeds]
    controls = [run_case(s, robots, seconds, change=False) for s in seeds]
    controls += [o for o in (real_case("intel"),) if o is not None]
    rows = [
        "| case | change | reported | after s | robot passes until reported | passes in the run |",
        "| --- | --- | --- | ---: | ---: | ---: |",
    ]
    total = found = 0
    for o in outcomes:
        for name, at, passes, passed in o.found:
            total += 1
            found += at is not None
            rows.append(
                f"| {o.name} | {name} | {'yes' if at is not None else 'no'} | "
                f"{'-' if at is None else f'{at:.0f}'} | {'-' if passes is None else passes} | "
                f"{passed} |"
            )
    false_rows = [
        "| case | reports | false added m2 | false removed m | scans | scans counted | "
        "update CPU ms/scan | map health CPU ms/scan | extra CPU | report CPU ms |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    false_rows += [
        f"| {o.name} | {len(o.reported)} | {o.false_area:.2f} | {o.false_length:.2f} | "
        f"{o.scans} | {o.counted} | {1e3 * o.update_cpu / o.scans:.3f} | "
        f"{1e3 * o.health_cpu / o.scans:.3f} | {100 * o.health_cpu / o.update_cpu:.1f} % | "
        f"{1e3 * o.report_cpu:.1f} |"
        for o in [*outcomes, *controls]
    ]
    every = [*outcomes, *controls]
    worst_area = max(o.false_area for o in every)
    worst_length = max(o.false_length for o in every)
    control_reports = sum(len(o.reported) for o in controls)
    extra = sum(o.health_cpu for o in every) / sum(o.update_cpu for o in every)
    lines = [
        "## Map health: changed buildings, people walking (issue 23)",
        "",
        f"Command: `{command}`. {robots} robots, {seconds:g} s at 10 Hz per case, 360 beams, "
        "1 cm noise, 8 people walking; see `bench/maphealth.py` for the cases and the grading.",
        "",
        "| target | measured | met |",
        "| --- | --- | --- |",
        f"| every added rack, blocked door and removed wall reported within 0.3 m | "
        f"{found} of {total} | {'yes' if found == total else 'no'} |",
        f"| at most 1 m2 of false `added`, 1 m of false `removed` per case | worst "
        f"{worst_area:.2f} m2, {worst_length:.2f} m | "
        f"{'yes' if worst_area <= 1 and worst_length <= 1 else 'no'} |",
        "| nothing reported where nothing changed (people only; the real log) | "
        f"{control_reports} reports | "
        f"{'yes' if control_reports == 0 else 'no'} |",
        f"| map health at most 5 % more CPU per scan | {100 * extra:.1f} % | "
        f"{'yes' if extra <= 0.05 else 'no'} |",
        "",
        *rows,
        "",
        *false_rows,
    ]
    if png is not None:
        draw(outcomes[0], png)
        lines += ["", f"![map health report]({png.as_posix()})"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    import sys

    parser = argparse.ArgumentParser(prog="python -m bench.maphealth", description=__doc__)
    parser.add_argument("--seeds", type=ints_text(0), default="1,2,3")
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=90.0)
    parser.add_argument("--png", type=Path, default=None, help="draw the first case's report")
    shown = " ".join(["python -m bench.maphealth", *(argv if argv is not None else sys.argv[1:])])

    def run(args: argparse.Namespace) -> str:
        seeds = [int(s) for s in args.seeds.split(",") if s]
        return render(seeds, args.robots, args.seconds, args.png, shown.replace(" --write", ""))

    return section_main(parser, run, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
