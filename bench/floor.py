"""Where a scan's CPU goes before any bus: the localizer, the engine around it, a worker's pipe.

Run: ``python -m bench.floor [--robots 20] [--steps 200] [--write]``.

The fleet benchmark (:mod:`bench.fleet`) measures the whole service; this one peels it, on the
same simulated fleet (:mod:`service.sim`, 360-beam scans at 10 Hz, drifting odometry), with no
Zenoh and no other process competing:

1. *localizer*: ``Localizer.update`` alone on the decoded scans (the motion from the odometry);
2. *engine*: each robot's odometry and scan payloads decoded (the JSON robots put) and handed
   to :class:`service.engine.FleetEngine`, as a worker does: the guard, the pose and its
   quality, map health evidence, the encoded PoseEstimate;
3. *behind a pipe*: the same payloads sent to a real worker process
   (:func:`service.live.worker.worker_main`) over its pipe, ``IN_FLIGHT`` batches at a time as
   the service sends them, the answers read back; the worker's CPU and the feeder's.

A second table splits the localizer's own cost: its tracking updates (no search) timed one by
one and grouped by the casts of the scan their refinement made, with the line through them:
the cost that grows with the casts (ray casting and the least squares, compiled) against the
part that does not (mostly Python), the most a compiled tracking step could save.

Each figure is CPU time (user + system) per scan over the measured steps, after every robot's
first :data:`WARM` steps (the first update searches wide, the kernels load). The differences
are what each layer costs; the rest of the service (the bus, the recorder, the views) is the
fleet benchmark's figure less the last row.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import multiprocessing as mp
import os
import platform
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from bench.report import section_main
from service.sim.plan import FleetPlan, FleetSpec, plan_fleet
from service.sim.wire import JsonWire, map_payload

SECTION = "floor"
#: Steps of every robot before the clock starts.
WARM = 20
#: Batches in a worker's pipe at once (the service's ``PIPE_IN_FLIGHT`` floor).
IN_FLIGHT = 16
T0 = 1_000_000_000
PERIOD = 100_000_000


def _measured(run: Callable[[int, int], int], steps: int) -> float:
    """CPU ms of this process per scan of ``run(WARM, steps)``, after ``run(1, WARM)``; ``run``
    returns the scans it handled."""
    run(1, WARM)
    c0 = _cpu()
    n = run(WARM, steps)
    return 1e3 * (_cpu() - c0) / n


def _cpu(pid: int | None = None) -> float:
    if pid is None:
        t = os.times()
        return t.user + t.system
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _plan(robots: int, steps: int, beams: int = 360) -> FleetPlan:
    return plan_fleet(FleetSpec(robots=robots, poses=steps + 1, seed=7, map_id="sim", beams=beams))


def _fleet(robots: int, steps: int) -> tuple[FleetPlan, JsonWire]:
    plan = _plan(robots, steps)
    return plan, JsonWire(plan)


def localizer_ms(plan: FleetPlan, steps: int) -> float:
    """CPU ms per ``Localizer.update`` over the plan's robots (scans decoded beforehand)."""
    from rlutf.localizer import Localizer, LocalizerConfig
    from rlutf.motion import relative

    config = LocalizerConfig()
    world = plan.world
    robots = [
        (Localizer(world, r.initial, config, seed=k), r)
        for k, r in enumerate(plan.robots)
        if r.initial is not None
    ]

    def run(a: int, b: int) -> int:
        n = 0
        for k in range(a, b):
            for loc, r in robots:
                loc.update(relative(r.odometry_at(k - 1), r.odometry_at(k)), r.scans[r.index(k)])
                n += 1
        return n

    return _measured(run, steps)


def localizer_alone_ms(beams: int, robots: int = 20, steps: int = 300) -> float:
    """CPU ms per ``Localizer.update`` of the localizer alone on ``beams``-beam scans
    (:func:`localizer_ms` on ``robots`` simulated robots, ``steps`` steps each): the same work in
    every hour, so a measure of the machine's speed beside a fleet run (``bench.fleet``) and the
    update time the service's CPU is fitted against (``bench.costfit``)."""
    return localizer_ms(_plan(robots, steps, beams), steps)


def update_costs(
    plan: FleetPlan, steps: int, compiled: dict[int, list[float]] | None = None
) -> dict[int, list[float]]:
    """CPU µs of each tracking update (no search: the prediction was accepted and refined) by
    the casts of the scan its refinement made, over the plan's robots after :data:`WARM` steps.

    Each update is timed by this thread's CPU clock, so the figures leave out time other
    processes took. With ``compiled``, the µs of each of those updates spent inside the
    localizer's compiled kernels (:func:`in_kernels`) go there, by casts likewise."""
    from rlutf.localizer import Localizer, LocalizerConfig
    from rlutf.motion import relative

    config = LocalizerConfig()
    robots = [
        (Localizer(plan.world, r.initial, config, seed=k), r)
        for k, r in enumerate(plan.robots)
        if r.initial is not None
    ]
    costs: dict[int, list[float]] = {}
    clock = time.thread_time_ns
    spent_in = [0]
    for k in range(1, steps):
        timing = compiled is not None and k >= WARM
        with in_kernels(spent_in) if timing else contextlib.nullcontext():
            for loc, r in robots:
                motion = relative(r.odometry_at(k - 1), r.odometry_at(k))
                scan = r.scans[r.index(k)]
                spent_in[0] = 0
                t0 = clock()
                result = loc.update(motion, scan)
                spent = (clock() - t0) / 1e3
                if k >= WARM and result.iterations == 0 and result.status == "tracking":
                    costs.setdefault(result.refine_casts, []).append(spent)
                    if compiled is not None:
                        compiled.setdefault(result.refine_casts, []).append(spent_in[0] / 1e3)
    return costs


#: The modules of the localizer's compiled kernels (numba), called from its Python code.
KERNEL_MODULES = ("rlutf._lm", "rlutf._kernels", "rlutf._grid", "rlutf._changes", "rlutf._bnb")


@contextlib.contextmanager
def in_kernels(spent: list[int]) -> Iterator[None]:
    """Within the block, every call from Python into a kernel of :data:`KERNEL_MODULES` adds
    the CPU ns of this thread it took to ``spent[0]``.

    Only the kernels no other kernel calls are wrapped (those that Python calls): a kernel
    compiled within the block may call the others, which must stay numba's own."""
    import importlib
    import inspect
    import re

    from numba.core.dispatcher import Dispatcher

    modules = [importlib.import_module(name) for name in KERNEL_MODULES]
    source = "\n".join(inspect.getsource(m) for m in modules)
    clock = time.thread_time_ns
    saved: list[tuple[Any, str, Any]] = []

    def timed(kernel: Any) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            t0 = clock()
            try:
                return kernel(*args)
            finally:
                spent[0] += clock() - t0

        return call

    for module in modules:
        for attr, value in list(vars(module).items()):
            if not isinstance(value, Dispatcher) or value.py_func.__module__ != module.__name__:
                continue
            if not re.search(rf"(?<!def )(?<![\w.]){attr}\(", source):  # no kernel calls it
                saved.append((module, attr, value))
                setattr(module, attr, timed(value))
    try:
        yield
    finally:
        for module, attr, value in saved:
            setattr(module, attr, value)


def cost_fit(costs: dict[int, list[float]]) -> tuple[float, float]:
    """``(fixed µs, µs per cast)``: the least-squares line through the median cost of each
    number of casts, weighted by the updates that made that many (medians: an update the
    scheduler or the allocator held up is an outlier, not a cost of its casts)."""
    if len(costs) < 2:
        return math.nan, math.nan
    casts = sorted(costs)
    x = np.array(casts, dtype=np.float64)
    y = np.array([float(np.median(costs[c])) for c in casts])
    w = np.sqrt(np.array([float(len(costs[c])) for c in casts]))
    per_cast, fixed = np.polyfit(x, y, 1, w=w)
    return float(fixed), float(per_cast)


def fleet_steps(plan: FleetPlan, wire: JsonWire, counted: Any = None) -> Callable[[int], int]:
    """A :class:`service.engine.FleetEngine` on the plan's map, every robot's first odometry
    and initial pose handled; returns what handles step ``k`` of every robot (its odometry,
    then its scan, decoded from the wire) and counts the scans. ``counted``: the map health
    evidence sink (default: the settings')."""
    from schemas import InitialPose, LaserScan, Odometry, decode
    from service.config import Settings
    from service.engine import FleetEngine
    from service.keys import Keys
    from service.live.worker import evidence, world_of_payload

    s = Settings()
    sink = counted if counted is not None else evidence(s.map_health)
    eng = FleetEngine(Keys(), s.localizer, int(s.event_interval_s * 1e9), None, sink)
    eng.register_map("sim", 1, world_of_payload(map_payload(plan)), 0)
    ids = [r.robot_id for r in plan.robots]
    for i, rid in enumerate(ids):
        eng.handle(rid, decode(Odometry, wire.odometry(i, 0, T0)), T0)
        start = wire.initial_pose(i, T0)
        if start is not None:
            eng.handle(rid, decode(InitialPose, start), T0)

    def step(k: int) -> int:
        st = T0 + k * PERIOD
        for i, rid in enumerate(ids):
            eng.handle(rid, decode(Odometry, wire.odometry(i, k, st)), st)
            eng.handle(rid, decode(LaserScan, wire.scan(i, k, st)), st + 1000)
        return len(ids)

    return step


def engine_ms(plan: FleetPlan, wire: JsonWire, steps: int) -> float:
    """CPU ms per scan of decoding a robot's odometry and scan and handling both."""
    step = fleet_steps(plan, wire)
    return _measured(lambda a, b: sum(step(k) for k in range(a, b)), steps)


def pipe_ms(plan: FleetPlan, wire: JsonWire, steps: int) -> tuple[float, float]:
    """CPU ms per scan of a worker process fed over its pipe, and of the feeding process."""
    from service.config import Settings
    from service.live.worker import recv, send, worker_main

    s = Settings()
    ctx = mp.get_context("spawn")
    conn, child = ctx.Pipe()
    args = (child, "rlutf", s.localizer, int(s.event_interval_s * 1e9), 2, None, s.map_health)
    proc = ctx.Process(target=worker_main, args=args, daemon=True)
    proc.start()
    child.close()
    try:
        if recv(conn)[0] != "ready":
            raise RuntimeError("the worker did not start")
        send(conn, ("map", "sim", 1, map_payload(plan), 0))
        ids = [r.robot_id for r in plan.robots]
        for i, rid in enumerate(ids):
            batch: list[tuple[str, bytes, int]] = [("odom", wire.odometry(i, 0, T0), T0)]
            start = wire.initial_pose(i, T0)
            if start is not None:
                batch.append(("initialpose", start, T0))
            send(conn, ("batch", rid, batch))
            recv(conn)

        def run(a: int, b: int) -> int:
            pending = n = 0
            for k in range(a, b):
                st = T0 + k * PERIOD
                for i, rid in enumerate(ids):
                    odom = ("odom", wire.odometry(i, k, st), st)
                    send(conn, ("batch", rid, [odom, ("scan", wire.scan(i, k, st), st + 1000)]))
                    pending, n = pending + 1, n + 1
                    while pending >= IN_FLIGHT:
                        _answer: Any = recv(conn)
                        pending -= 1
            for _ in range(pending):
                recv(conn)
            return n

        run(1, WARM)
        w0, f0 = _cpu(proc.pid), _cpu()
        n = run(WARM, steps)
        return 1e3 * (_cpu(proc.pid) - w0) / n, 1e3 * (_cpu() - f0) / n
    finally:
        send(conn, ("stop",))
        proc.join(10)


def render(args: argparse.Namespace) -> str:
    """Measure the three layers and return the section."""
    plan, wire = _fleet(args.robots, args.steps)
    started = time.time()
    loc = localizer_ms(plan, args.steps)
    compiled: dict[int, list[float]] = {}
    costs = update_costs(plan, args.steps, compiled)  # right after: the machine's speed drifts
    eng = engine_ms(plan, wire, args.steps)
    worker, feeder = pipe_ms(plan, wire, args.steps)
    scans = args.robots * (args.steps - WARM)
    engine = "engine: payloads decoded, `FleetEngine.handle` (odometry and scan)"
    rows = [
        ("localizer: `Localizer.update` on decoded scans", loc, "-"),
        (engine, eng, f"{eng - loc:+.3f}"),
        ("behind a pipe: a worker, fed as the service feeds it", worker, f"{worker - eng:+.3f}"),
        ("the feeding process's side of the pipe", feeder, "-"),
    ]
    return "\n".join(
        [
            f"Command: `python -m bench.floor --robots {args.robots} --steps {args.steps} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}; {args.robots} simulated robots, {scans} scans "
            f"measured per row (after {WARM} steps each), one process at a time (the worker "
            f"row: two, the worker and its feeder); {time.time() - started:.0f} s in all. Load "
            f"average at the end: {os.getloadavg()[0]:.1f}.",
            "",
            "| layer | CPU ms per scan | added by the layer |",
            "| --- | ---: | ---: |",
            *(f"| {name} | {ms:.3f} | {more} |" for name, ms, more in rows),
            "",
            *_cost_table(costs, compiled),
        ]
    )


def _cost_table(costs: dict[int, list[float]], compiled: dict[int, list[float]]) -> list[str]:
    """The tracking updates by casts, the line through them, and their time in the kernels."""
    fixed, per_cast = cost_fit(costs)
    total = sum(len(v) for v in costs.values())
    mean_casts = sum(c * len(v) for c, v in costs.items()) / max(total, 1)
    lines = [
        f"The tracking updates (the prediction accepted and refined, no search: {total} of "
        f"them) by the casts of the scan their refinement made, each timed by its thread's CPU "
        "clock; *in the kernels*: the part of each spent inside the localizer's compiled "
        "kernels (numba), timed around each call Python makes into one (`bench.floor.in_kernels`"
        "), *outside*: the rest (Python, numpy, shapely, numba's call overhead):",
        "",
        "| casts | updates | median µs | mean µs | in the kernels, median µs "
        "| outside, median µs |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for c in sorted(costs):
        v, k = costs[c], compiled.get(c, [])
        rest = [a - b for a, b in zip(v, k, strict=True)] if len(k) == len(v) else []
        inside = f"{float(np.median(k)):.0f}" if rest else "-"
        outside = f"{float(np.median(rest)):.0f}" if rest else "-"
        lines.append(
            f"| {c} | {len(v)} | {float(np.median(v)):.0f} | {float(np.mean(v)):.0f} | "
            f"{inside} | {outside} |"
        )
    all_v = [x for v in costs.values() for x in v]
    all_k = [x for k in compiled.values() for x in k]
    lines += [
        "",
        f"Least-squares line through the medians (weighted by updates): **{fixed:.0f} µs fixed + "
        f"{per_cast:.0f} "
        f"µs per cast**; {mean_casts:.2f} casts on average, so "
        f"{100 * fixed / (fixed + per_cast * mean_casts):.0f} % of an average tracking update "
        "is the part that does not grow with the casts.",
    ]
    if all_k and len(all_k) == len(all_v):
        mean_v, mean_k = float(np.mean(all_v)), float(np.mean(all_k))
        lines += [
            "",
            f"Of an average tracking update ({mean_v:.0f} µs), **{mean_k:.0f} µs "
            f"({100 * mean_k / mean_v:.0f} %) run inside the compiled kernels** and "
            f"{mean_v - mean_k:.0f} µs outside them: the most a tracking step compiled whole "
            "could save (the timing wraps add about a microsecond to the outside part).",
        ]
    return lines


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.floor",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=20, help="simulated robots")
    p.add_argument("--steps", type=int, default=200, help="steps per robot (10 per second)")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
