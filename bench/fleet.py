"""The largest fleet one service instance holds at 10 Hz on this machine (issue 3 target).

Run: ``python -m bench.fleet [--robots 25,50,100,150] [--duration 20] [--write]``.

For each fleet size, a ``rlutf serve`` subprocess (router on a loopback port, embedded store,
worker processes, recording on unless ``--no-record``) serves a load-generator process that
publishes, for every robot, odometry and a 360-beam scan at 10 Hz (phases staggered) from a
simulated run precomputed before the clock starts, and times each scan put to its pose put.
The generator shares the two cores with the service, as robots' traffic handling would on a
real host. Reported: scan-to-pose latency percentiles, scans sent, poses received, scans the
service reports dropped (superseded before processing) or not processed, the difference
(uncounted; in brackets, how many of those the service reports as processed, i.e. poses
published but not received), the CPU time per scan sent of the service's main process, of its
workers and of the generator over the publishing interval (where the two cores go), and the
service's resident memory (main process plus workers) sampled every second.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.report import section_main
from bench.threads import python_thread_names, task_cpu, thread_table

SECTION = "fleet"
RATE_HZ = 10.0
#: Scans of each robot not timed: its first scan after the initial pose searches wide (a few ms
#: each, every robot at once), which is start-up, not the steady state the targets are about.
WARMUP_STEPS = int(2 * RATE_HZ)


def _rss_tree_mb(pid: int) -> float:
    """Resident memory of a process and its children, MB (from /proc)."""
    total = 0
    for p in [pid, *_children(pid)]:
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1])
        except OSError:
            continue
    return total / 1024.0


def _cpu_seconds(pid: int) -> float:
    """User plus system CPU time of one process so far, seconds (from /proc)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine_steal() -> tuple[int, int]:
    """CPU time stolen by the hypervisor and all CPU time of the machine so far, in ticks.

    On a shared virtual machine, other guests take CPU time that never shows in this
    machine's load; when they do, latency and CPU per scan rise without any change here.
    """
    with open("/proc/stat") as f:
        ticks = [int(v) for v in f.readline().split()[1:]]
    return ticks[7], sum(ticks[:8])


def _children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid``."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        found.append(int(entry))
            except OSError:
                continue
    return found


def timed_publishing(
    robots: int,
    steps: int,
    t0: int,
    send: Any,
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
) -> tuple[int, float, float]:
    """The timed loop of a load generator: ``send(robot, step, stamp)`` at 10 Hz per robot.

    Phases are staggered over the period. Sets ``ready``, waits for ``go``, and sets ``began``
    and ``ended`` around the loop.

    Returns:
        Scans sent, how far the loop ended behind its schedule (s), and its CPU time (s).
    """
    import resource

    ready.set()
    go.wait()
    time.sleep(1.0)
    began.set()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu0 = usage.ru_utime + usage.ru_stime
    start = time.monotonic()
    period = 1.0 / RATE_HZ
    scans_sent = 0
    when = 0.0
    # in time order: robot i's k-th scan at (k + i / robots) periods, generated as they come so
    # that a long run (bench.soak) holds no schedule in memory
    for k in range(steps - 1):
        for i in range(robots):
            when = k * period + (i / robots) * period
            delay = start + when - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            send(i, k, t0 + int((k + 1) * period * 1e9))
            scans_sent += 1
    behind = time.monotonic() - (start + when)
    ended.set()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return scans_sent, behind, usage.ru_utime + usage.ru_stime - cpu0


def generator_result(
    scans_sent: int, poses: int, latencies: list[float], behind: float, cpu: float
) -> dict[str, Any]:
    """What a load generator hands back to :func:`run_size`."""
    return {
        "scans_sent": scans_sent,
        "poses": poses,
        "latencies": latencies,
        "generator_behind_s": behind,
        "generator_cpu_s": cpu,
    }


def open_fleet(
    endpoint: str,
    world: Any,
    starts: list[tuple[str, Any, Any]],
    on_pose: Any,
    congestion_control: Any = None,
) -> tuple[list[Any], Any, list[tuple[Any, Any]], int]:
    """Connect a load generator's robots: the map, their first odometry and initial pose.

    Opens one Zenoh session per 12 robots (1 to 8), puts ``world`` as map ``bench``, subscribes
    ``on_pose`` to every robot's pose, then for each ``(robot id, first odometry pose, true
    start pose)`` puts the odometry and an InitialPose stamped ``t0`` and declares the robot's
    odometry and scan publishers, with ``congestion_control`` when given (Zenoh's default,
    drop, otherwise).

    Returns:
        The sessions, the pose subscriber, per robot its (odometry, scan) publishers, and t0 (ns).
    """
    import zenoh

    from schemas import InitialPose, Map, encode
    from service.live.sessions import client_config

    robots = len(starts)
    qos = {} if congestion_control is None else {"congestion_control": congestion_control}
    sessions = [zenoh.open(client_config(endpoint)) for _ in range(max(1, min(8, robots // 12)))]
    op = sessions[0]
    op.put(
        "rlutf/maps/bench",
        encode(
            Map.model_validate({"map_id": "bench", "version": 1, "geometry": world.to_geojson()})
        ),
    )
    sub = op.declare_subscriber("rlutf/robots/*/pose", on_pose)
    time.sleep(1.0)
    t0 = time.time_ns()
    pubs = []
    for idx, (rid, o, p) in enumerate(starts):
        sess = sessions[idx % len(sessions)]
        sess.put(
            f"rlutf/robots/{rid}/odom",
            json.dumps({"stamp_ns": t0, "x": float(o[0]), "y": float(o[1]), "theta": float(o[2])}),
        )
        op.put(
            f"rlutf/robots/{rid}/initialpose",
            encode(
                InitialPose(
                    stamp_ns=t0, map_id="bench", x=float(p[0]), y=float(p[1]), theta=float(p[2])
                )
            ),
        )
        pubs.append(
            (
                sess.declare_publisher(f"rlutf/robots/{rid}/odom", **qos),
                sess.declare_publisher(f"rlutf/robots/{rid}/scan", **qos),
            )
        )
    return sessions, sub, pubs, t0


def _generator(
    endpoint: str,
    robots: int,
    duration: float,
    seed: int,
    out: Any,
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
) -> None:
    """Load generator (a separate process): precompute, then publish and time.

    Sets ``began`` and ``ended`` around the timed publishing, so that the parent can read the
    service's CPU time over the same interval.
    """
    from rlutf.sim import (
        LidarModel,
        OdometryModel,
        drift_odometry,
        make_building,
        make_trajectory,
        simulate_scan,
    )

    rng = np.random.default_rng(seed)
    world = make_building(rng)
    steps = int(duration * RATE_HZ) + 1
    lidar = LidarModel(beams=360)
    plans = []
    for i in range(robots):
        truth = make_trajectory(world, rng, steps, dt=1.0 / RATE_HZ)
        odom = drift_odometry(truth, OdometryModel(), rng)
        scans = []
        for k in range(steps):
            s = simulate_scan(world, truth[k], lidar, rng)
            ranges = [round(float(r), 4) if math.isfinite(r) else None for r in s.ranges]
            scans.append((s.angle_min, s.angle_increment, s.range_min, s.range_max, ranges))
        plans.append((f"r{i:03d}", truth, odom, scans))
    sent: dict[tuple[str, int], int] = {}
    latencies: list[float] = []
    poses = 0
    lock = threading.Lock()

    def on_pose(sample: Any) -> None:
        nonlocal poses
        now = time.time_ns()
        d = json.loads(sample.payload.to_bytes())
        with lock:
            t = sent.pop((d["robot_id"], d["stamp_ns"]), None)
            poses += 1
            if t is not None:
                latencies.append((now - t) / 1e6)

    starts = [(rid, odom[0], truth[0]) for rid, truth, odom, _ in plans]
    sessions, sub, pubs, t0 = open_fleet(endpoint, world, starts, on_pose)
    # payloads encoded now, stamped at publication: only puts happen in the timed loop
    encoded = []
    for rid, _, odom, scans in plans:
        rows = []
        for k in range(1, steps):
            a0, inc, rmin, rmax, ranges = scans[k]
            rows.append(
                (
                    json.dumps(
                        {"x": float(odom[k][0]), "y": float(odom[k][1]), "theta": float(odom[k][2])}
                    )[1:],
                    json.dumps(
                        {
                            "angle_min": a0,
                            "angle_increment": inc,
                            "range_min": rmin,
                            "range_max": rmax,
                            "ranges": ranges,
                        }
                    )[1:],
                )
            )
        encoded.append((rid, rows))

    def send(i: int, k: int, stamp: int) -> None:
        rid, rows = encoded[i]
        odom_rest, scan_rest = rows[k]
        head = f'{{"stamp_ns": {stamp}, '
        pubs[i][0].put(head + odom_rest)
        if k >= WARMUP_STEPS:
            with lock:
                sent[(rid, stamp)] = time.time_ns()
        pubs[i][1].put(head + scan_rest)

    scans_sent, behind, cpu = timed_publishing(robots, steps, t0, send, ready, go, began, ended)
    time.sleep(2.0)  # the last poses
    sub.undeclare()
    for s in sessions:
        s.close()
    out.put(generator_result(scans_sent, poses, latencies, behind, cpu))


def start_service(
    endpoint: str,
    tmp: Path,
    record: bool,
    workers: int,
    serve_flags: tuple[str, ...] = (),
    env: dict[str, str] | None = None,
    stderr: Any = subprocess.DEVNULL,
) -> subprocess.Popen[bytes]:
    """Start ``rlutf serve`` as a router on ``endpoint``, its store (and logs) under ``tmp``.

    Args:
        endpoint: the Zenoh endpoint to listen on.
        tmp: folder for the map store (``store``) and the recording (``logs``).
        record: record MCAP logs.
        workers: service worker processes.
        serve_flags: more flags for ``rlutf serve``.
        env: extra environment variables (``RLUTF_*`` settings).
        stderr: where the service's log goes (``subprocess.Popen``'s argument).
    """
    exe = shutil.which("rlutf", path=str(Path(sys.executable).parent)) or "rlutf"
    cmd = [
        exe,
        "serve",
        "--listen",
        endpoint,
        "--store",
        str(tmp / "store"),
        "--instance",
        "fleetbench",
        "--workers",
        str(workers),
    ]
    cmd += ["--record", str(tmp / "logs")] if record else ["--no-record"]
    cmd += serve_flags
    full_env = None if env is None else {**os.environ, **env}
    return subprocess.Popen(cmd, stderr=stderr, env=full_env)


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


def run_size(
    robots: int,
    duration: float,
    record: bool,
    workers: int,
    generator: Any = None,
    serve_flags: tuple[str, ...] = (),
    threads: bool = False,
) -> dict[str, Any]:
    """One fleet size against a fresh service subprocess.

    ``generator`` (default: the JSON robots of :func:`_generator`, same arguments) and
    ``serve_flags`` let another front door be measured the same way (:mod:`bench.ros2`).
    With ``threads``, the result's ``threads`` holds the service's CPU per scan sent by thread
    (:mod:`bench.threads`), main process and workers apart.
    """
    from service.live.sessions import free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-fleet-"))
    proc = start_service(endpoint, tmp, record, workers, serve_flags)
    ctx = mp.get_context("spawn")
    out, ready, go, began, ended = ctx.Queue(), ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    gen = ctx.Process(
        target=generator or _generator,
        args=(endpoint, robots, duration, 7, out, ready, go, began, ended),
    )
    try:
        time.sleep(2.0)
        gen.start()
        ready.wait(600)
        rss: list[float] = []
        stop = threading.Event()

        def sample() -> None:
            while not stop.wait(1.0):
                rss.append(_rss_tree_mb(proc.pid))

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        go.set()
        began.wait(60)
        workers_pids = _children(proc.pid)
        steal0 = machine_steal()
        main0 = _cpu_seconds(proc.pid)
        workers0 = sum(_cpu_seconds(p) for p in workers_pids)
        tasks0 = {p: task_cpu(p) for p in [proc.pid, *workers_pids]}
        ended.wait(duration + 120)
        main_cpu = _cpu_seconds(proc.pid) - main0
        steal1 = machine_steal()
        workers_cpu = sum(_cpu_seconds(p) for p in workers_pids) - workers0
        tasks1 = {p: task_cpu(p) for p in tasks0}
        result = out.get(timeout=60)
        health = _health(endpoint)
        by_thread: dict[str, dict[str, float]] = {}
        if threads:
            for p, start in tasks0.items():
                table = by_thread.setdefault("main" if p == proc.pid else "workers", {})
                names = python_thread_names(p)
                for name, ms in thread_table(start, tasks1[p], names, result["scans_sent"]):
                    table[name] = table.get(name, 0.0) + ms
        stop.set()
        gen.join(10)
    finally:
        stop_service(proc)
        shutil.rmtree(tmp, ignore_errors=True)
    lat = np.asarray(result["latencies"]) if result["latencies"] else np.array([math.nan])
    dropped = int(health.get("dropped", -1))
    # scans the service took but could not turn into a pose (no map yet, too few returns)
    lost_no_pose = int(health.get("extra", {}).get("scans_not_processed", 0))
    return {
        "robots": robots,
        "sent": result["scans_sent"],
        "poses": result["poses"],
        "dropped": dropped,
        "not_processed": lost_no_pose,
        "uncounted": result["scans_sent"] - result["poses"] - dropped - lost_no_pose,
        "p50": float(np.percentile(lat, 50)),
        "p99": float(np.percentile(lat, 99)),
        "max": float(lat.max()),
        "rss_peak": max(rss) if rss else math.nan,
        "rss_first": rss[0] if rss else math.nan,
        "rss_last": rss[-1] if rss else math.nan,
        "behind": result["generator_behind_s"],
        "compute_p50": float(health.get("extra", {}).get("compute_ms", {}).get("p50", math.nan)),
        # receipt of the scan to publication of its pose, inside the service
        "service_p99": float(health.get("latency_ms", {}).get("p99", math.nan)),
        "lost": int(health.get("extra", {}).get("lost", -1)),
        "relocalizations": int(health.get("extra", {}).get("relocalizations", -1)),
        # CPU time per scan sent, ms: where the two cores go
        "cpu_main": 1e3 * main_cpu / max(result["scans_sent"], 1),
        "cpu_workers": 1e3 * workers_cpu / max(result["scans_sent"], 1),
        "cpu_generator": 1e3 * result["generator_cpu_s"] / max(result["scans_sent"], 1),
        # share of the machine's CPU time the hypervisor gave to other guests meanwhile
        "steal": 100.0 * (steal1[0] - steal0[0]) / max(steal1[1] - steal0[1], 1),
        "processed": int(health.get("processed", -1)),
        "threads": by_thread,
        # service CPU per scan it turned into a pose, ms (dropped scans cost little)
        "cpu_service_per_pose": 1e3
        * (main_cpu + workers_cpu)
        / max(int(health.get("processed", 0)), 1),
    }


def _health(endpoint: str) -> dict[str, Any]:
    import zenoh

    from service.live.sessions import client_config

    with zenoh.open(client_config(endpoint)) as s:
        return query_health(s)


def query_health(session: Any, timeout: float = 3.0) -> dict[str, Any]:
    """The first Health reply of ``rlutf/service/*/health`` on an open session (empty if none)."""
    for r in session.get("rlutf/service/*/health", timeout=timeout):
        if r.ok is not None:
            return dict(json.loads(r.ok.payload.to_bytes()))
    return {}


def thread_rows(by_thread: dict[str, dict[str, float]]) -> list[str]:
    """Markdown rows: CPU ms per scan sent by process and thread, largest first."""
    rows = []
    for process, table in by_thread.items():
        for name, ms in sorted(table.items(), key=lambda item: -item[1]):
            if ms >= 0.005:
                rows.append(f"| {process} | {name} | {ms:.3f} |")
    return rows


def render(
    sizes: list[int], duration: float, record: bool, workers: int, threads: bool = False
) -> str:
    """Run every size and return the Markdown section."""
    rows = []
    by_thread: dict[str, dict[str, float]] = {}
    held = 0
    load = os.getloadavg()[0]
    need: list[tuple[float, int, float, float]] = []
    for n in sizes:
        r = run_size(n, duration, record, workers, threads=threads)
        by_thread = r["threads"] or by_thread
        need.append(
            (
                r["cpu_service_per_pose"] + r["cpu_generator"],
                n,
                r["cpu_service_per_pose"],
                r["cpu_generator"],
            )
        )
        ok = r["p99"] <= 50.0 and r["uncounted"] == 0 and r["dropped"] <= 0.01 * r["sent"]
        held = n if ok else held
        rows.append(
            f"| {n} | {r['sent']} | {r['poses']} | {r['dropped']} | {r['not_processed']} "
            f"| {r['uncounted']} ({r['processed'] - r['poses']}) "
            f"| {r['p50']:.1f} | {r['p99']:.1f} | {r['max']:.0f} | {r['service_p99']:.1f} "
            f"| {r['compute_p50']:.2f} "
            f"| {r['cpu_main']:.2f} / {r['cpu_workers']:.2f} / {r['cpu_generator']:.2f} "
            f"| {r['steal']:.1f} "
            f"| {r['rss_first']:.0f} / {r['rss_peak']:.0f} / {r['rss_last']:.0f} "
            f"| {'yes' if ok else 'no'} |"
        )
        print(rows[-1], flush=True)
    best = min(need)
    sizes_arg = ",".join(str(s) for s in sizes)
    flags = ("" if record else " --no-record") + (f" --workers {workers}" if workers >= 0 else "")
    flags += " --threads" if threads else ""
    return "\n".join(
        [
            f"Command: `python -m bench.fleet --robots {sizes_arg} --duration {duration:g}"
            f"{flags} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}. One `rlutf serve` (recording "
            f"{'on' if record else 'off'}) and one load-generator process share the cores; "
            f"{duration:g} s per size at 10 Hz per robot, 360-beam scans, 1 cm noise; latency "
            f"from each robot's scan put to its pose received, over every scan after the "
            f"robot's first {WARMUP_STEPS / RATE_HZ:g} s (its first scan after the initial "
            "pose searches wide); drops, counts and CPU over the whole run. "
            f"Load average when the run started: {load:.1f} (2 cores; above 0 means other work "
            "was competing for them).",
            "",
            "| robots | scans sent | poses | dropped (reported) | not processed (reported) "
            "| uncounted (of which published, not received) | latency p50 ms "
            "| p99 ms | max ms "
            "| service p99 ms (receipt to publication, its last 10,000 scans, start included) "
            "| worker compute p50 ms "
            "| CPU ms per scan: service main / workers / generator "
            "| CPU stolen by the hypervisor, % "
            "| service RSS MB first / peak / last "
            "| held (p99 <= 50 ms, drops <= 1 %, none uncounted) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- "
            "| --- |",
            *rows,
            "",
            f"Largest fleet held: **{held} robots**." if held else "No size was held.",
            "",
            # CPU ms per scan at 10 Hz per robot is cores per 100 robots: 1000 scans/s x ms.
            f"CPU budget: the cheapest measured cost per scan ({best[1]} robots) was "
            f"{best[2]:.2f} ms of service CPU per pose published plus {best[3]:.2f} ms of the "
            f"generator per scan sent; at that cost 100 robots at 10 Hz need {best[0]:.1f} "
            f"cores, of the {os.cpu_count()} here.",
            *(
                [
                    "",
                    f"Where the service's CPU goes at {sizes[-1]} robots: CPU ms per scan sent, "
                    "by thread (the kernel's per-thread counters over the publishing interval; "
                    "Python thread names from `py-spy dump`; threads doing the same job added "
                    "up, both workers added up).",
                    "",
                    "| process | thread | CPU ms per scan |",
                    "| --- | --- | ---: |",
                    *thread_rows(by_thread),
                ]
                if by_thread
                else []
            ),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.fleet",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", default="25,50,100,150", help="fleet sizes, comma-separated")
    p.add_argument("--duration", type=float, default=20.0, help="seconds per size")
    p.add_argument("--no-record", action="store_true", help="service without MCAP recording")
    p.add_argument("--workers", type=int, default=-1, help="service worker processes")
    p.add_argument(
        "--threads",
        action="store_true",
        help="also report the service's CPU per scan by thread (names need py-spy)",
    )

    def run(args: argparse.Namespace) -> str:
        sizes = [int(s) for s in args.robots.split(",")]
        return render(sizes, args.duration, not args.no_record, args.workers, args.threads)

    return section_main(p, run, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
