"""``rlutf demo``: the service on its embedded defaults with a simulated fleet, shown live.

Everything is real: the same service as ``rlutf serve`` in its default layout (a Zenoh router in
this process, the file-backed map store, the service processes behind it or, with ``--workers``,
one :class:`~service.live.node.LocalizationService` and its worker processes, the MCAP recorder),
an operator session that puts the map and the initial poses, and Zenoh client sessions of
simulated robots (:mod:`service.sim`, one session per robot) publishing drifting odometry and
noisy scans. Only the robots' motion and sensors are simulated, which is what gives a ground
truth to show the error against.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.console import Console
from rich.live import Live
from rich.table import Table

from service.config import Settings
from service.keys import Keys
from service.live.host import Host
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.recording import make_recorder
from service.sim.fleet import SimFleet, drawing_bar, drive
from service.sim.plan import FleetSpec, plan_fleet
from service.sim.score import RobotScore, Scoreboard
from service.sim.wire import JsonWire

MAP_ID = "demo-building"


def live_table(scores: list[RobotScore], title: str) -> Table:
    """The live table: each robot's last pose against the truth."""
    t = Table(title=title)
    for col in (
        "robot",
        "scans",
        "poses",
        "status",
        "error cm",
        "1-sigma cm",
        "heading deg",
        "1-sigma deg",
        "odometry-only error cm",
        "latency p50 ms",
        "p99 ms",
    ):
        t.add_column(col, justify="right")
    for v in scores:
        last = v.errors[-1] * 100 if v.errors else math.nan
        head = v.heading_errors[-1] if v.heading_errors else math.nan
        t.add_row(
            v.robot_id,
            str(v.sent),
            str(v.poses),
            v.last_status,
            f"{last:.1f}",
            f"{v.last_sigma[0]:.2f}",
            f"{head:.2f}",
            f"{v.last_sigma[1]:.3f}",
            f"{v.last_odometry_error * 100:.1f}",
            f"{v.latency_ms(50):.1f}",
            f"{v.latency_ms(99):.1f}",
        )
    return t


def summary_table(scores: list[RobotScore]) -> Table:
    """Per-robot accuracy and latency over the whole run."""
    t = Table(title="summary (errors against the simulated truth)")
    for col in (
        "robot",
        "poses / scans",
        "RMSE cm",
        "max cm",
        "heading RMSE deg",
        "final odometry-only error cm",
        "latency p50 ms",
        "p99 ms",
        "statuses",
    ):
        t.add_column(col, justify="right")
    for v in scores:
        if not v.errors:
            t.add_row(v.robot_id, f"0 / {v.sent}", *["-"] * 7)
            continue
        e = np.asarray(v.errors)
        h = np.asarray(v.heading_errors)
        statuses = ", ".join(f"{k} {n}" for k, n in sorted(v.statuses.items()))
        t.add_row(
            v.robot_id,
            f"{len(e)} / {v.sent}",
            f"{math.sqrt(np.mean(e**2)) * 100:.1f}",
            f"{e.max() * 100:.1f}",
            f"{math.sqrt(np.mean(h**2)):.2f}",
            f"{v.last_odometry_error * 100:.1f}",
            f"{v.latency_ms(50):.1f}",
            f"{v.latency_ms(99):.1f}",
            statuses,
        )
    return t


def demo_spec(args: argparse.Namespace, named: bool = True) -> FleetSpec:
    """The fleet of ``rlutf demo``'s flags; ``named=False``: without the robots' ids, for
    sizing it (``--robots 100000000`` made ids for 22 GB before it was found too big)."""
    return FleetSpec(
        robots=args.robots,
        poses=int(args.duration * args.rate) + 2,
        rate_hz=args.rate,
        beams=args.beams,
        seed=args.seed,
        map_id=MAP_ID,
        robot_ids=tuple(f"robot-{i + 1:02d}" for i in range(args.robots)) if named else (),
    )


def demo_layout(args: argparse.Namespace) -> dict[str, Any]:
    """The settings of the demo's ``--workers`` and ``--processes``, those given."""
    flags = {"workers": args.workers, "processes": args.processes}
    return {k: v for k, v in flags.items() if v is not None}


def run_demo(args: argparse.Namespace, console: Console | None = None) -> int:
    """Run the demo on ``console`` (default: stdout's); returns the exit code (1 if no robot
    got a pose)."""
    console = console or Console(stderr=False)
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    spec = demo_spec(args)
    with drawing_bar(spec.robots) as advance:
        plan = plan_fleet(spec, on_robot=advance)
    with tempfile.TemporaryDirectory(prefix="rlutf-demo-") as tmp:
        store = args.store or Path(tmp) / "store"
        settings = Settings(
            listen=[endpoint],
            store_dir=store,
            record_dir=args.record,
            no_record=args.no_record,
            instance="demo",
            **demo_layout(args),
        )
        processes = settings.service_processes()
        console.print(
            f"[bold]rlutf demo[/bold]: service on {endpoint}, map store {store}, "
            + ("no recording" if args.no_record else f"recording to {args.record}/")
        )
        # Returns once every process or worker can localize: the robots' clocks start only then.
        say = lambda message: console.print(f"service: {message}")  # noqa: E731
        service: Host | LocalizationService
        if processes > 0:
            service = Host(settings.model_copy(update={"processes": processes})).start(say)
            console.print(f"service: {processes} service processes behind the router")
        else:
            service = LocalizationService(settings, recorder=make_recorder(settings)).start(say)
        stop = threading.Event()
        try:
            fleet = SimFleet(
                plan, JsonWire(plan), lambda: zenoh.open(client_config(endpoint)), args.robots
            )
            try:
                put = fleet.store_map()
                if not put.stored:  # the demo's own store: it takes it, unless it cannot write
                    console.print(f"rlutf demo: {put.said}")
                    return 1
                console.print(
                    f"operator: put map {MAP_ID} version {put.version} "
                    f"({len(plan.world.segments)} walls); "
                    f"{args.robots} robots at {args.rate:g} Hz, {args.beams} beams, "
                    f"{args.duration:g} s"
                )
                t0 = time.time_ns()
                board = Scoreboard(plan, t0)
                sub = fleet.operator.declare_subscriber(
                    Keys().all_poses,
                    lambda s: board.on_pose(s.payload.to_bytes(), time.time_ns()),
                )
                fleet.start(t0)

                def send(robot: int, step: int) -> None:
                    fleet.odometry(robot, step, board.stamp(step))
                    board.sent(robot, step, time.time_ns())
                    fleet.scan(robot, step, board.stamp(step))

                steps = int(args.duration * args.rate)
                robots = threading.Thread(
                    target=drive,
                    args=(args.robots, 1.0 / args.rate, send, steps, stop),
                    name="demo-fleet",
                    daemon=True,
                )
                robots.start()
                try:
                    if args.quiet:
                        robots.join()
                    else:
                        end = time.monotonic() + args.duration
                        table = live_table(board.snapshot(), "live")
                        with Live(table, console=console, refresh_per_second=4) as live:
                            while robots.is_alive():
                                robots.join(0.25)
                                left = max(end - time.monotonic(), 0.0)
                                live.update(
                                    live_table(board.snapshot(), f"live ({left:.0f} s left)")
                                )
                except KeyboardInterrupt:
                    console.print("interrupted")
                stop.set()
                robots.join(5.0)
                time.sleep(0.5)
                sub.undeclare()
            finally:
                fleet.close()
            health = (
                service.health(fresh=True) if isinstance(service, Host) else service.health()
            ).decode()
        finally:
            service.close()
        scores = board.snapshot()
        console.print(summary_table(scores))
        h = json.loads(health)
        if args.verbose_health:
            console.print_json(health)
        console.print(
            f"service: received {h['received']}, processed {h['processed']}, "
            f"dropped {h['dropped']}, rejected {h['rejected']}; scan-to-pose latency "
            f"p50 {h['latency_ms']['p50']:.1f} ms, p99 {h['latency_ms']['p99']:.1f} ms"
        )
        return 0 if sum(s.poses for s in scores) > 0 else 1
