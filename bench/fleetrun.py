"""One fleet size against a fresh ``rlutf serve``: the service subprocess, the load generator
process (the simulated fleet of :mod:`service.sim`) and what is measured of both.

Shared by :mod:`bench.fleet`, :mod:`bench.ros2`, :mod:`bench.soak` and
:mod:`bench.relocalize_fleet`.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.procstat import cpu_seconds, descendants, machine_steal, pss_tree_mb, rss_tree_mb
from bench.threads import python_thread_names, task_cpu, task_switches, thread_table

RATE_HZ = 10.0
#: Scans of each robot not timed: its first scan after the initial pose searches wide (a few ms
#: each, every robot at once), which is start-up, not the steady state the targets are about.
WARMUP_STEPS = int(2 * RATE_HZ)
#: The seed of the fleet's plan.
SEED = 7


def serve_layout(workers: int | None, processes: int | None) -> tuple[int, int]:
    """``(workers, processes)`` that ``rlutf serve`` runs with a benchmark's ``--workers`` and
    ``--processes`` (``None``: not given). Neither given is the service's default layout, as
    :meth:`service.config.Settings.service_processes` resolves it here; ``--workers`` alone is
    the layout of workers."""
    from service.config import Settings

    if processes is None:
        processes = 0 if workers is not None else Settings().service_processes()
    return (-1 if workers is None else workers), processes


def layout_text(processes: int) -> str:
    """The layout of ``processes`` service processes (0: the layout of workers), in words."""
    if processes:
        return f"{processes} service processes behind the router"
    return "one process and its worker processes"


def start_service(
    endpoint: str,
    tmp: Path,
    record: bool,
    workers: int | None,
    serve_flags: tuple[str, ...] = (),
    env: dict[str, str] | None = None,
    stderr: Any = subprocess.DEVNULL,
    instance: str = "fleetbench",
) -> subprocess.Popen[bytes]:
    """Start ``rlutf serve`` as a router on ``endpoint``, its store (and logs) under ``tmp``.

    Args:
        endpoint: the Zenoh endpoint to listen on.
        tmp: folder for the map store (``store``) and the recording (``logs``).
        record: record MCAP logs.
        workers: service worker processes (``None``: no ``--workers``, the service's default
            layout).
        serve_flags: more flags for ``rlutf serve``.
        env: extra environment variables (``RLUTF_*`` settings).
        stderr: where the service's log goes (``subprocess.Popen``'s argument).
        instance: the instance's name.
    """
    exe = shutil.which("rlutf", path=str(Path(sys.executable).parent)) or "rlutf"
    cmd = [exe, "serve", "--listen", endpoint, "--store", str(tmp / "store")]
    cmd += ["--instance", instance]
    cmd += [] if workers is None else ["--workers", str(workers)]
    cmd += ["--record", str(tmp / "logs")] if record else ["--no-record"]
    cmd += serve_flags
    full_env = None if env is None else {**os.environ, **env}
    proc = subprocess.Popen(cmd, stderr=stderr, env=full_env)
    wait_ready(endpoint, proc, instance=instance)
    return proc


def wait_ready(
    endpoint: str,
    proc: subprocess.Popen[bytes],
    timeout: float = 600.0,
    instance: str | None = None,
) -> None:
    """Block until the service on ``endpoint`` is ready: its liveliness token is declared only
    once every worker can localize (the first start after an install compiles the kernels).
    With ``instance``, until that instance's Health says ``ready`` (a host of processes is
    ready once all of them are).

    Raises:
        RuntimeError: the service exited first, or was not ready within ``timeout`` seconds.
    """
    import zenoh

    from service.live.sessions import client_config

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(
                f"rlutf serve exited with code {proc.returncode} before it was ready"
            )
        try:
            with zenoh.open(client_config(endpoint)) as session:
                if instance is not None:
                    if query_health(session, 1.0, instance).get("ready"):
                        return
                else:
                    tokens = session.liveliness().get("rlutf/service/*", timeout=1.0)
                    if any(reply.ok is not None for reply in tokens):
                        return
        except zenoh.ZError:
            pass  # the router is not listening yet
        time.sleep(0.2)
    raise RuntimeError(f"rlutf serve on {endpoint} was not ready within {timeout:g} s")


def stop_service(proc: subprocess.Popen[bytes], timeout: float = 20.0) -> int | None:
    """SIGTERM (an orderly stop), then kill after ``timeout`` seconds.

    Returns:
        The exit code of an orderly stop, ``None`` when it had to be killed.
    """
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None


def query_health(session: Any, timeout: float = 3.0, instance: str = "*") -> dict[str, Any]:
    """The first Health reply of ``rlutf/service/{instance}/health`` on an open session (empty
    if none)."""
    for r in session.get(f"rlutf/service/{instance}/health", timeout=timeout):
        if r.ok is not None:
            return dict(json.loads(r.ok.payload.to_bytes()))
    return {}


def health(endpoint: str, instance: str = "*") -> dict[str, Any]:
    """The first Health reply of the service at ``endpoint`` (empty if none)."""
    import zenoh

    from service.live.sessions import client_config

    with zenoh.open(client_config(endpoint)) as s:
        return query_health(s, instance=instance)


def timed_publishing(
    robots: int,
    steps: int,
    send: Callable[[int, int], None],
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
) -> tuple[int, float, float]:
    """A load generator's timed run: ``send(robot, step)`` for steps 1 to ``steps`` at 10 Hz.

    Sets ``ready``, waits for ``go``, and sets ``began`` and ``ended`` around the run (so that
    the parent reads the service's CPU time over the same interval); :func:`service.sim.fleet.drive`
    keeps the schedule.

    Returns:
        Scans sent, how far the run ended behind its schedule (s), and its CPU time (s).
    """
    from service.sim.fleet import drive

    ready.set()
    go.wait()
    time.sleep(1.0)
    began.set()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu0 = usage.ru_utime + usage.ru_stime
    sent, _, behind = drive(robots, 1.0 / RATE_HZ, send, steps)
    ended.set()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return sent, behind, usage.ru_utime + usage.ru_stime - cpu0


def _pose_listener(door: str) -> tuple[str, Callable[[Any], tuple[str, int]]]:
    """The key expression of the poses the robots of ``door`` read, and (robot, stamp) of one."""
    if door == "json":
        return "rlutf/robots/*/pose", lambda s: _json_pose(s.payload.to_bytes())
    from service.ros2 import convert

    def ros(sample: Any) -> tuple[str, int]:
        h = convert.deserialize(sample.payload.to_bytes(), convert.POSE_COV).header
        return str(sample.key_expr).split("/")[1], convert.stamp_ns(h)

    return "0/*/amcl_pose/*/*", ros


def _json_pose(payload: bytes) -> tuple[str, int]:
    d = json.loads(payload)
    return str(d["robot_id"]), int(d["stamp_ns"])


def fleet_generator(
    endpoint: str,
    robots: int,
    duration: float,
    door: str,
    out: Any,
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
    beams: int = 360,
) -> None:
    """Load generator (a separate process): plan, then publish and time each scan to its pose.

    ``door``: ``json`` (WIRE.md's robots) or ``ros2`` (ROS 2 robots on rmw_zenoh's keys, whose
    pose is ``amcl_pose``). The fleet is :mod:`service.sim`'s, seed :data:`SEED`, map ``bench``,
    ``beams`` beams a scan.
    """
    import zenoh

    from service.live.sessions import client_config
    from service.sim.fleet import SimFleet
    from service.sim.plan import FleetSpec, plan_fleet
    from service.sim.wire import CdrWire, JsonWire

    steps = int(duration * RATE_HZ) + 1
    spec = FleetSpec(
        robots=robots, poses=steps, rate_hz=RATE_HZ, seed=SEED, map_id="bench", beams=beams
    )
    plan = plan_fleet(spec)
    wire = JsonWire(plan) if door == "json" else CdrWire(plan)
    ids = [r.robot_id for r in plan.robots]
    sent: dict[tuple[str, int], int] = {}
    latencies: list[float] = []
    poses = 0
    timed = 0  # scans sent after their robot's first WARMUP_STEPS
    lock = threading.Lock()
    key, robot_and_stamp = _pose_listener(door)

    def on_pose(sample: Any) -> None:
        nonlocal poses
        now = time.time_ns()
        which = robot_and_stamp(sample)
        with lock:
            t = sent.pop(which, None)
            poses += 1
            if t is not None:
                latencies.append((now - t) / 1e6)

    fleet = SimFleet(plan, wire, lambda: zenoh.open(client_config(endpoint)))
    fleet.put_map()
    sub = fleet.operator.declare_subscriber(key, on_pose)
    time.sleep(1.0)
    t0 = time.time_ns()
    fleet.start(t0)
    period = spec.period_ns

    def send(i: int, step: int) -> None:
        nonlocal timed
        stamp = t0 + step * period
        fleet.odometry(i, step, stamp)
        if step > WARMUP_STEPS:
            with lock:
                sent[(ids[i], stamp)] = time.time_ns()
                timed += 1
        fleet.scan(i, step, stamp)

    scans_sent, behind, cpu = timed_publishing(robots, steps - 1, send, ready, go, began, ended)
    time.sleep(2.0)  # the last poses
    sub.undeclare()
    fleet.close()
    out.put(
        {
            "scans_sent": scans_sent,
            "poses": poses,
            "latencies": latencies,
            "timed": timed,
            "generator_behind_s": behind,
            "generator_cpu_s": cpu,
        }
    )


def run_size(
    robots: int,
    duration: float,
    record: bool,
    workers: int,
    door: str = "json",
    serve_flags: tuple[str, ...] = (),
    threads: bool = False,
    env: dict[str, str] | None = None,
    beams: int = 360,
) -> dict[str, Any]:
    """One fleet size against a fresh service subprocess.

    ``door`` and ``serve_flags`` let another front door be measured the same way
    (:mod:`bench.ros2`); ``env`` adds variables to the service's environment
    (:mod:`bench.ownedkeys`); ``beams``: beams a scan (:mod:`bench.costfit`). With ``threads``,
    the result's ``threads`` holds the service's CPU per scan sent by thread
    (:mod:`bench.threads`), main process and workers apart (host and its other service processes
    apart with ``--processes``).
    """
    from service.live.sessions import free_port

    hosted = "--processes" in serve_flags
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-fleet-"))
    proc = start_service(endpoint, tmp, record, workers, serve_flags, env=env)
    ctx = mp.get_context("spawn")
    out, ready, go, began, ended = ctx.Queue(), ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    gen = ctx.Process(
        target=fleet_generator,
        args=(endpoint, robots, duration, door, out, ready, go, began, ended, beams),
    )
    rss: list[float] = []
    pss: list[float] = []
    stop = threading.Event()
    finished = False
    try:
        time.sleep(2.0)
        gen.start()
        ready.wait(600)

        def sample() -> None:
            while not stop.wait(1.0):
                rss.append(rss_tree_mb(proc.pid))
                pss.append(pss_tree_mb(proc.pid))

        threading.Thread(target=sample, daemon=True).start()
        go.set()
        began.wait(60)
        workers_pids = descendants(proc.pid)
        steal0 = machine_steal()
        main0 = cpu_seconds(proc.pid)
        workers0 = {p: cpu_seconds(p) for p in workers_pids}
        tasks0 = {p: task_cpu(p) for p in [proc.pid, *workers_pids]}
        switches0 = {p: task_switches(p) for p in tasks0}
        ended.wait(duration + 120)
        main_cpu = cpu_seconds(proc.pid) - main0
        steal1 = machine_steal()
        # A child that ended meanwhile (a map checker idle for a while) is not read again: its
        # CPU since the start is left out (it was idle, or it would not have ended).
        ends = {p: cpu_seconds(p) for p in workers_pids}
        workers_cpu = sum(ends[p] - workers0[p] for p in ends if not math.isnan(ends[p]))
        tasks1 = {p: task_cpu(p) for p in tasks0}
        switches1 = {p: task_switches(p) for p in tasks0}
        result = out.get(timeout=60)
        h = health(endpoint, "fleetbench")
        by_thread: dict[str, dict[str, float]] = {}
        switches: dict[str, dict[str, float]] = {}
        if threads:
            for p, start in tasks0.items():
                # A host of service processes (--processes) runs process 0 itself.
                labels = ("host", "processes") if hosted else ("main", "workers")
                label = labels[0] if p == proc.pid else labels[1]
                names = python_thread_names(p)
                sent = result["scans_sent"]
                for into, rows in (
                    (by_thread, thread_table(start, tasks1[p], names, sent)),
                    (switches, thread_table(switches0[p], switches1[p], names, sent, scale=1.0)),
                ):
                    table = into.setdefault(label, {})
                    for name, value in rows:
                        table[name] = table.get(name, 0.0) + value
        gen.join(10)
        finished = True
    finally:
        stop.set()
        stop_service(proc)
        # read once the service has closed its files; not after a failed run, whose own error
        # must not be hidden behind one about its logs
        recorded = scans_recorded(tmp / "logs") if record and finished else None
        shutil.rmtree(tmp, ignore_errors=True)
    row = _figures(
        robots,
        result,
        h,
        rss,
        main_cpu,
        workers_cpu,
        steal1[0] - steal0[0],
        steal1[1] - steal0[1],
        by_thread,
    )
    row["switches"] = switches  # context switches per scan sent, by thread (with ``threads``)
    row["pss_peak"] = max(pss) if pss else math.nan
    # scans that never reached an owner's log: lost on the bus before the service took them in
    row["never_recorded"] = None if recorded is None else row["sent"] - recorded
    return row


def scans_recorded(folder: Path) -> int:
    """The scans the service's processes recorded in ``folder``: every scan an owner took in,
    whatever became of it (from the files' summaries: no message is read)."""
    from schemas import SCHEMA_NAMES, LaserScan
    from service.logs.mcapread import LogFile

    total = 0
    for path in sorted(folder.glob("*.mcap")):
        with LogFile(path) as log:
            total += log.count([SCHEMA_NAMES[LaserScan]])
    return total


def _figures(
    robots: int,
    result: dict[str, Any],
    h: dict[str, Any],
    rss: list[float],
    main_cpu: float,
    workers_cpu: float,
    stolen: int,
    ticks: int,
    by_thread: dict[str, dict[str, float]],
) -> dict[str, Any]:
    """The row of one size: what the generator timed, what the service reported and cost."""
    lat = np.asarray(result["latencies"]) if result["latencies"] else np.array([math.nan])
    extra = h.get("extra", {})
    dropped = int(h.get("dropped", -1))
    # scans the service took but could not turn into a pose (no map yet, too few returns)
    not_processed = int(extra.get("scans_not_processed", 0))
    sent = result["scans_sent"]
    return {
        "robots": robots,
        "sent": sent,
        "poses": result["poses"],
        "dropped": dropped,
        "not_processed": not_processed,
        "uncounted": sent - result["poses"] - dropped - not_processed,
        # of the scans sent after each robot's first WARMUP_STEPS, the share answered
        "answered_after": len(result["latencies"]) / max(result["timed"], 1),
        "p50": float(np.percentile(lat, 50)),
        "p99": float(np.percentile(lat, 99)),
        "max": float(lat.max()),
        "rss_peak": max(rss) if rss else math.nan,
        "rss_first": rss[0] if rss else math.nan,
        "rss_last": rss[-1] if rss else math.nan,
        "behind": result["generator_behind_s"],
        "compute_p50": float(extra.get("compute_ms", {}).get("p50", math.nan)),
        # receipt of the scan to publication of its pose, inside the service
        "service_p99": float(h.get("latency_ms", {}).get("p99", math.nan)),
        "lost": int(extra.get("lost", -1)),
        "relocalizations": int(extra.get("relocalizations", -1)),
        # CPU time per scan sent, ms: where the two cores go
        "cpu_main": 1e3 * main_cpu / max(sent, 1),
        "cpu_workers": 1e3 * workers_cpu / max(sent, 1),
        "cpu_generator": 1e3 * result["generator_cpu_s"] / max(sent, 1),
        # share of the machine's CPU time the hypervisor gave to other guests meanwhile
        "steal": 100.0 * stolen / max(ticks, 1),
        "processed": int(h.get("processed", -1)),
        "threads": by_thread,
        # service CPU per scan it turned into a pose, ms (dropped scans cost little)
        "cpu_service_per_pose": 1e3 * (main_cpu + workers_cpu) / max(int(h.get("processed", 0)), 1),
    }
