"""``rlutf demo``: the service on its embedded defaults with a simulated fleet, shown live.

Everything is real: the same :class:`~service.live.node.LocalizationService` as ``rlutf serve`` (a
Zenoh router in this process, the file-backed map store, worker processes, the MCAP recorder),
an operator session that puts the map and the initial poses, and one Zenoh client session per
simulated robot publishing drifting odometry and noisy scans at 10 Hz. Only the robots' motion
and sensors are simulated (:mod:`rlutf.sim`), which is what gives a ground truth to show the
error against.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.console import Console
from rich.live import Live
from rich.table import Table

from rlutf.motion import wrap_scalar
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)
from schemas import (
    InitialPose,
    LaserScan,
    Map,
    Odometry,
    PoseEstimate,
    SensorOffset,
    decode,
    encode,
)
from service.config import Settings
from service.keys import Keys
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.recording import make_recorder

JSON = zenoh.Encoding.APPLICATION_JSON
MAP_ID = "demo-building"


@dataclass
class RobotView:
    """What the demo knows and shows about one simulated robot."""

    robot_id: str
    truth: dict[int, np.ndarray] = field(default_factory=dict)
    odom_error: dict[int, float] = field(default_factory=dict)
    sent_at: dict[int, int] = field(default_factory=dict)
    errors: list[float] = field(default_factory=list)
    heading_errors: list[float] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    statuses: dict[str, int] = field(default_factory=dict)
    last_status: str = "-"
    last_sigma: tuple[float, float] = (math.nan, math.nan)
    last_dr_error: float = 0.0
    sent: int = 0


class Fleet:
    """Simulated robots, each publishing on its own Zenoh client session."""

    def __init__(self, args: argparse.Namespace, endpoint: str, world: Any) -> None:
        self.args = args
        self.endpoint = endpoint
        self.world = world
        self.keys = Keys()
        self.stop = threading.Event()
        self.views: dict[str, RobotView] = {}
        self.lock = threading.Lock()
        steps = int(args.duration * args.rate) + 2
        rng = np.random.default_rng(args.seed + 1)
        self.paths: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for i in range(args.robots):
            rid = f"robot-{i + 1:02d}"
            truth = make_trajectory(world, rng, steps, dt=1.0 / args.rate)
            odom = drift_odometry(truth, OdometryModel(), rng)
            self.paths[rid] = (truth, odom)
            self.views[rid] = RobotView(rid)
        self.threads: list[threading.Thread] = []

    def initial_poses(self, session: zenoh.Session, stamp: int) -> None:
        """The operator tells the service where each robot starts."""
        for rid, (truth, _) in self.paths.items():
            p = truth[0]
            msg = InitialPose(
                stamp_ns=stamp, map_id=MAP_ID, x=float(p[0]), y=float(p[1]), theta=float(p[2])
            )
            session.put(self.keys.robot(rid, "initialpose"), encode(msg), encoding=JSON)

    def start(self, t0: int) -> None:
        """Start one thread (and session) per robot."""
        for i, rid in enumerate(self.paths):
            t = threading.Thread(
                target=self._drive, args=(rid, i, t0), daemon=True, name=f"demo-{rid}"
            )
            self.threads.append(t)
            t.start()

    def _drive(self, rid: str, index: int, t0: int) -> None:
        truth, odom = self.paths[rid]
        view = self.views[rid]
        rng = np.random.default_rng(self.args.seed * 1000 + index)
        lidar = LidarModel(beams=self.args.beams)
        period = 1.0 / self.args.rate
        start = time.monotonic()
        with zenoh.open(client_config(self.endpoint)) as session:
            scan_pub = session.declare_publisher(self.keys.robot(rid, "scan"), encoding=JSON)
            odom_pub = session.declare_publisher(self.keys.robot(rid, "odom"), encoding=JSON)
            o = odom[0]
            odom_pub.put(
                encode(Odometry(stamp_ns=t0, x=float(o[0]), y=float(o[1]), theta=float(o[2])))
            )
            for i in range(1, len(truth)):
                wait = start + i * period - time.monotonic()
                if self.stop.wait(max(wait, 0.0)):
                    break
                stamp = t0 + int(i * period * 1e9)
                o = odom[i]
                odom_pub.put(
                    encode(
                        Odometry(stamp_ns=stamp, x=float(o[0]), y=float(o[1]), theta=float(o[2]))
                    )
                )
                scan = simulate_scan(self.world, truth[i], lidar, rng)
                ranges = [float(r) if math.isfinite(r) else None for r in scan.ranges]
                msg = LaserScan(
                    stamp_ns=stamp,
                    angle_min=scan.angle_min,
                    angle_increment=scan.angle_increment,
                    range_min=scan.range_min,
                    range_max=scan.range_max,
                    ranges=ranges,
                    sensor_offset=SensorOffset(),
                )
                with self.lock:
                    view.truth[stamp] = truth[i]
                    view.odom_error[stamp] = self._dead_reckoning_error(truth, odom, i)
                    view.sent_at[stamp] = time.time_ns()
                    view.sent += 1
                scan_pub.put(encode(msg))

    @staticmethod
    def _dead_reckoning_error(truth: np.ndarray, odom: np.ndarray, i: int) -> float:
        # odometry starts at the true start pose, so its error is its drift
        return float(math.hypot(*(odom[i, :2] - truth[i, :2])))

    def on_pose(self, sample: zenoh.Sample) -> None:
        """Score a published pose against the truth at its scan's stamp."""
        now = time.time_ns()
        try:
            pose = decode(PoseEstimate, sample.payload.to_bytes())
        except Exception:
            return
        view = self.views.get(pose.robot_id)
        if view is None:
            return
        with self.lock:
            truth = view.truth.pop(pose.stamp_ns, None)
            sent = view.sent_at.pop(pose.stamp_ns, None)
            dr = view.odom_error.pop(pose.stamp_ns, None)
            if truth is None:
                return
            view.errors.append(math.hypot(pose.x - truth[0], pose.y - truth[1]))
            view.heading_errors.append(abs(math.degrees(wrap_scalar(pose.theta - truth[2]))))
            if sent is not None:
                view.latencies_ms.append((now - sent) / 1e6)
            view.statuses[pose.status] = view.statuses.get(pose.status, 0) + 1
            view.last_status = pose.status
            view.last_sigma = _sigma_cm(pose.covariance)
            view.last_dr_error = dr or 0.0

    def table(self, title: str) -> Table:
        """The live table."""
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
        with self.lock:
            for rid, v in self.views.items():
                last = v.errors[-1] * 100 if v.errors else float("nan")
                head = v.heading_errors[-1] if v.heading_errors else float("nan")
                lat = np.percentile(v.latencies_ms, [50, 99]) if v.latencies_ms else [math.nan] * 2
                t.add_row(
                    rid,
                    str(v.sent),
                    str(len(v.errors)),
                    v.last_status,
                    f"{last:.1f}",
                    f"{v.last_sigma[0]:.2f}",
                    f"{head:.2f}",
                    f"{v.last_sigma[1]:.3f}",
                    f"{v.last_dr_error * 100:.1f}",
                    f"{lat[0]:.1f}",
                    f"{lat[1]:.1f}",
                )
        return t

    def summary(self) -> Table:
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
        with self.lock:
            for rid, v in self.views.items():
                if not v.errors:
                    t.add_row(rid, f"0 / {v.sent}", *["-"] * 7)
                    continue
                e = np.asarray(v.errors)
                h = np.asarray(v.heading_errors)
                lat = np.percentile(v.latencies_ms, [50, 99]) if v.latencies_ms else [math.nan] * 2
                statuses = ", ".join(f"{k} {n}" for k, n in sorted(v.statuses.items()))
                t.add_row(
                    rid,
                    f"{len(e)} / {v.sent}",
                    f"{math.sqrt(np.mean(e**2)) * 100:.1f}",
                    f"{e.max() * 100:.1f}",
                    f"{math.sqrt(np.mean(h**2)):.2f}",
                    f"{v.last_dr_error * 100:.1f}",
                    f"{lat[0]:.1f}",
                    f"{lat[1]:.1f}",
                    statuses,
                )
        return t


def _sigma_cm(covariance: tuple[float, ...] | None) -> tuple[float, float]:
    """One-sigma position (cm, the root of the position covariance's trace) and heading (deg)
    of a PoseEstimate's covariance; NaN without one."""
    if covariance is None:
        return (math.nan, math.nan)
    position = math.sqrt(max(covariance[0] + covariance[4], 0.0)) * 100
    return (position, math.degrees(math.sqrt(max(covariance[8], 0.0))))


def run_demo(args: argparse.Namespace) -> int:
    """Run the demo; returns the exit code (1 if no robot got a pose)."""
    console = Console(stderr=False)
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="rlutf-demo-") as tmp:
        store = args.store or Path(tmp) / "store"
        settings = Settings(
            listen=[endpoint],
            store_dir=store,
            record_dir=args.record,
            no_record=args.no_record,
            workers=args.workers,
            instance="demo",
        )
        console.print(
            f"[bold]rlutf demo[/bold]: service on {endpoint}, map store {store}, "
            + ("no recording" if args.no_record else f"recording to {args.record}/")
        )
        world = make_building(np.random.default_rng(args.seed))
        fleet = Fleet(args, endpoint, world)
        # Returns once every worker can localize: the robots' clocks start only then.
        service = LocalizationService(settings, recorder=make_recorder(settings)).start(
            lambda message: console.print(f"service: {message}")
        )
        try:
            with zenoh.open(client_config(endpoint)) as operator:
                payload = encode(
                    Map.model_validate(
                        {"map_id": MAP_ID, "version": 1, "geometry": world.to_geojson()}
                    )
                )
                operator.put(Keys().map(MAP_ID), payload, encoding=JSON)
                console.print(
                    f"operator: put map {MAP_ID} ({len(world.segments)} walls); "
                    f"{args.robots} robots at {args.rate:g} Hz, {args.beams} beams, "
                    f"{args.duration:g} s"
                )
                sub = operator.declare_subscriber(Keys().all_poses, fleet.on_pose)
                time.sleep(0.5)
                t0 = time.time_ns()
                fleet.start(t0)
                fleet.initial_poses(operator, t0)
                end = time.monotonic() + args.duration
                try:
                    if args.quiet:
                        while time.monotonic() < end:
                            time.sleep(0.2)
                    else:
                        with Live(
                            fleet.table("live"), console=console, refresh_per_second=4
                        ) as live:
                            while time.monotonic() < end:
                                time.sleep(0.25)
                                left = max(end - time.monotonic(), 0.0)
                                live.update(fleet.table(f"live ({left:.0f} s left)"))
                except KeyboardInterrupt:
                    console.print("interrupted")
                fleet.stop.set()
                for t in fleet.threads:
                    t.join(5.0)
                time.sleep(0.5)
                sub.undeclare()
                health = service.health().decode()
        finally:
            service.close()
        console.print(fleet.summary())
        h = json.loads(health)
        if args.verbose_health:
            console.print_json(health)
        console.print(
            f"service: received {h['received']}, processed {h['processed']}, "
            f"dropped {h['dropped']}, rejected {h['rejected']}; scan-to-pose latency "
            f"p50 {h['latency_ms']['p50']:.1f} ms, p99 {h['latency_ms']['p99']:.1f} ms"
        )
        poses = sum(len(v.errors) for v in fleet.views.values())
        return 0 if poses > 0 else 1
