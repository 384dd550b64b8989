"""Running a soak (:mod:`bench.soak`): the service, the looped load generator, the samples, and
reading the logs after an orderly stop."""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import queue
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.fleetrun import (
    RATE_HZ,
    query_health,
    start_service,
    stop_service,
    timed_publishing,
)
from bench.procstat import (
    MEMORY_PARTS,
    cpu_seconds,
    descendants,
    labelled_processes,
    process_memory_mb,
    pss_tree_mb,
    rss_tree_mb,
)
from bench.soakplan import FileCheck, LatencyHistogram

#: The instance name ``start_service`` gives the service (a host answers for its processes).
INSTANCE = "fleetbench"

#: Longest wait, after the last scan, for the service to drain before the final counts, s.
DRAIN_S = 60.0
#: A scan whose pose has not come after this long is forgotten by the generator (dropped).
_FORGET_NS = 30_000_000_000


def _generator(
    endpoint: str,
    robots: int,
    minutes: float,
    loop_seconds: float,
    seed: int,
    out: Any,
    ready: Any,
    go: Any,
    began: Any,
    ended: Any,
    requests: Any,
    replies: Any,
    finish: Any,
) -> None:
    """Load generator (a separate process): loops precomputed, then publish, time, report.

    Answers each request ``n`` on ``requests`` with the figures so far on ``replies``; after the
    last scan, waits for ``finish`` (the service has drained) before its final figures.
    """
    import zenoh

    from service.live.sessions import client_config
    from service.sim.fleet import SimFleet
    from service.sim.plan import FleetSpec, plan_fleet
    from service.sim.wire import JsonWire

    # Each robot drives a path of half a loop and back (service.sim.plan): what the generator
    # holds is fixed by the loop's length, not by the run's.
    forward = max(2, round(loop_seconds * RATE_HZ / 2) + 1)
    spec = FleetSpec(robots=robots, poses=forward, rate_hz=RATE_HZ, seed=seed, map_id="bench")
    plan = plan_fleet(spec)
    rids = [r.robot_id for r in plan.robots]

    sent: dict[tuple[str, int], int] = {}
    latencies: list[float] = []
    counts = {"sent": 0, "poses": 0}
    lock = threading.Lock()
    hist = LatencyHistogram()

    def on_pose(sample: Any) -> None:
        now = time.time_ns()
        d = json.loads(sample.payload.to_bytes())
        with lock:
            t = sent.pop((d["robot_id"], d["stamp_ns"]), None)
            counts["poses"] += 1
            if t is not None:
                latencies.append((now - t) / 1e6)

    def figures() -> dict[str, Any]:
        now = time.time_ns()
        with lock:
            lat = np.asarray(latencies)
            latencies.clear()
            for key in [k for k, t in sent.items() if now - t > _FORGET_NS]:
                del sent[key]
            snapshot = dict(counts)
        hist.add(lat)
        p50, p99, top = np.percentile(lat, [50, 99, 100]) if len(lat) else (math.nan,) * 3
        return {**snapshot, "p50": p50, "p99": p99, "max": top, "count": len(lat)}

    def answer() -> None:
        while (n := requests.get()) is not None:
            replies.put((n, figures()))

    # Blocking publishers: a scan the generator's own transport dropped (Zenoh's default when
    # its queue is full, as on two starved cores) would be counted by no one; blocked, the
    # generator falls behind its schedule instead, and says so.
    fleet = SimFleet(
        plan,
        JsonWire(plan),
        lambda: zenoh.open(client_config(endpoint)),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    fleet.put_map()
    sub = fleet.operator.declare_subscriber("rlutf/robots/*/pose", on_pose)
    time.sleep(1.0)
    t0 = time.time_ns()
    fleet.start(t0)
    threading.Thread(target=answer, daemon=True).start()

    def send(i: int, step: int) -> None:
        stamp = t0 + step * spec.period_ns
        fleet.odometry(i, step, stamp)
        with lock:
            sent[(rids[i], stamp)] = time.time_ns()
            counts["sent"] += 1
        fleet.scan(i, step, stamp)

    steps = int(minutes * 60 * RATE_HZ)
    scans_sent, behind, cpu = timed_publishing(robots, steps, send, ready, go, began, ended)
    finish.wait(120)
    last = figures()
    sub.undeclare()
    fleet.close()
    out.put(
        {
            "scans_sent": scans_sent,
            "poses": last["poses"],
            "behind_s": behind,
            "cpu_s": cpu,
            "p50": hist.percentile(50),
            "p99": hist.percentile(99),
            "max": float(np.nonzero(hist.counts)[0].max(initial=-1) + 1) * hist.BIN_MS,
        }
    )


class _Sampler:
    """The parent's view of the service and the generator, one :meth:`take` per sample."""

    def __init__(self, proc: Any, gen: Any, session: Any, requests: Any, replies: Any) -> None:
        self.proc, self.gen, self.session = proc, gen, session
        self._processes: dict[str, int] | None = None
        self.requests, self.replies = requests, replies
        self.t0 = time.monotonic()
        self.main0 = cpu_seconds(proc.pid)
        self.workers: dict[int, float] = {p: cpu_seconds(p) for p in descendants(proc.pid)}
        self.workers0 = sum(self.workers.values())
        self.gen0 = cpu_seconds(gen.pid)
        self.n = 0

    def cpu(self) -> tuple[float, float, float]:
        """CPU seconds since the start: service main, its workers (each as last seen), generator."""
        for p in descendants(self.proc.pid):
            c = cpu_seconds(p)
            if math.isfinite(c):
                self.workers[p] = c
        return (
            cpu_seconds(self.proc.pid) - self.main0,
            sum(self.workers.values()) - self.workers0,
            cpu_seconds(self.gen.pid) - self.gen0,
        )

    def _generator_figures(self, timeout: float) -> dict[str, Any]:
        self.n += 1
        self.requests.put(self.n)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                n, fig = self.replies.get(timeout=left)
            except queue.Empty:
                break
            if n == self.n:
                return dict(fig)
        return {}

    def memory(self) -> dict[str, float]:
        """Each service process's resident memory by part, flat (``mem_{process}_{part}``, MB;
        ``nan`` once a process is gone), for the processes of the first sample."""
        if self._processes is None:
            self._processes = labelled_processes(self.proc.pid)
        out: dict[str, float] = {}
        for label, pid in self._processes.items():
            m = process_memory_mb(pid) or {}
            out.update({f"mem_{label}_{part}": m.get(part, math.nan) for part in MEMORY_PARTS})
        return out

    def take(self, timeout: float) -> dict[str, Any]:
        """One sample (see the module docstring); ``nan`` where a figure did not come."""
        minute = (time.monotonic() - self.t0) / 60.0
        main, workers, gen_cpu = self.cpu()
        h = query_health(self.session, timeout=timeout, instance=INSTANCE)
        extra = h.get("extra", {})
        g = self._generator_figures(timeout)
        lat = h.get("latency_ms", {})
        nan = math.nan
        return {
            "minute": minute,
            "rss_service_mb": rss_tree_mb(self.proc.pid),
            "pss_service_mb": pss_tree_mb(self.proc.pid),
            "rss_generator_mb": rss_tree_mb(self.gen.pid),
            **self.memory(),
            "cpu_main_s": main,
            "cpu_workers_s": workers,
            "cpu_generator_s": gen_cpu,
            "sent": g.get("sent", nan),
            "poses": g.get("poses", nan),
            "latency_p50_ms": g.get("p50", nan),
            "latency_p99_ms": g.get("p99", nan),
            "latency_max_ms": g.get("max", nan),
            "received": h.get("received", nan),
            "processed": h.get("processed", nan),
            "dropped": h.get("dropped", nan),
            "not_processed": extra.get("scans_not_processed", nan),
            "pending_inputs": extra.get("pending_inputs", nan),
            "recorder_queue": extra.get("recorder_queue", nan),
            "recorder_overflow": extra.get("recorder_overflow", nan),
            "service_latency_p99_ms": lat.get("p99", nan) if lat else nan,
        }


class _HeapSnapshots:
    """``--tracemalloc N``: every service process traces Python's allocations
    (:mod:`service.live.heapdumps`), snapshotted after the warm-up and at the end of the load."""

    def __init__(self, folder: Path, frames: int) -> None:
        self.folder, self.frames = folder, frames
        folder.mkdir()
        self.taken = 0
        self.pids: dict[str, int] = {}

    def env(self) -> dict[str, str]:
        from service.live.heapdumps import ENV_DIR, ENV_FRAMES

        return {ENV_FRAMES: str(self.frames), ENV_DIR: str(self.folder)}

    def take(self, service_pid: int, timeout: float = 120.0) -> None:
        """Signal every process of the service, wait until each wrote its snapshot."""
        from service.live.heapdumps import snapshots

        self.pids = self.pids or labelled_processes(service_pid)
        self.taken += 1
        for pid in self.pids.values():
            os.kill(pid, signal.SIGUSR2)
        deadline = time.monotonic() + timeout
        sizes: list[int] = []
        while time.monotonic() < deadline:
            time.sleep(1.0)
            found = [snapshots(self.folder, pid) for pid in self.pids.values()]
            now = [f[-1].stat().st_size for f in found if len(f) >= self.taken]
            if len(now) == len(self.pids) and now == sizes:  # all written, sizes settled
                return
            sizes = now
        raise RuntimeError(f"tracemalloc snapshots not written within {timeout:g} s")

    def growth(self) -> dict[str, Any]:
        """Per process: its traced allocations' growth, kB, and the largest places."""
        from service.live.heapdumps import grown, snapshots

        out: dict[str, Any] = {}
        for label, pid in self.pids.items():
            found = snapshots(self.folder, pid)
            if len(found) >= 2:
                total, rows = grown(found[0], found[-1])
                out[label] = {"total_kb": total, "rows": [vars(r) for r in rows]}
        return out


def check_logs(record_dir: Path) -> tuple[list[FileCheck], list[str]]:
    """Every finished log file read end to end, and the names of ``.part`` files left."""
    from schemas import SCHEMA_NAMES, PoseEstimate
    from service.logs.mcapread import LogError, LogFile
    from service.logs.runs import run_tag

    pose_schema = SCHEMA_NAMES[PoseEstimate]
    checks = []
    for path in sorted(record_dir.glob("*.mcap")):
        messages = poses = indexed = 0
        first, last = math.inf, -math.inf
        error = tag = None
        try:
            with LogFile(path) as log:
                tag = run_tag(log)
                indexed = log.count()
                for record in log.messages():
                    messages += 1
                    # the span of the poses: a file starts with the maps (and their views) at
                    # their original log_time
                    if record.schema_name == pose_schema:
                        poses += 1
                        first = min(first, record.log_time_ns)
                        last = max(last, record.log_time_ns)
        except LogError as err:
            error = str(err)
        span = (last - first) / 1e9 if last >= first else math.nan
        checks.append(
            FileCheck(
                path.name,
                path.stat().st_size,
                messages,
                indexed,
                poses,
                span,
                error,
                tag.run_id if tag is not None else None,
                tag.sequence if tag is not None else None,
            )
        )
    return checks, sorted(p.name for p in record_dir.glob("*.part"))


def _progress(s: dict[str, Any]) -> None:
    print(
        f"[soak {s['minute']:5.1f} min] service {s['rss_service_mb']:.0f} MB (Pss "
        f"{s['pss_service_mb']:.0f}: shared pages once), generator "
        f"{s['rss_generator_mb']:.0f} MB; sent {s['sent']}, poses {s['poses']}, dropped "
        f"{s['dropped']}, not processed {s['not_processed']}; latency p50 "
        f"{s['latency_p50_ms']:.1f} p99 {s['latency_p99_ms']:.1f} ms; pending "
        f"{format_count(s['pending_inputs'])}, recorder queue "
        f"{format_count(s['recorder_queue'])}, overflow {s['recorder_overflow']}",
        file=sys.stderr,
        flush=True,
    )


def _wait_drained(session: Any, timeout: float) -> float:
    """After the last scan: wait until the service has no input pending and its counts of scans
    processed, dropped and not processed stay put for a second (scans still in the service would
    be neither answered nor counted yet).

    Returns:
        Seconds waited (``timeout`` when it did not drain).
    """
    start = time.monotonic()
    before: tuple[Any, ...] = ()
    while (waited := time.monotonic() - start) < timeout:
        h = query_health(session, timeout=2.0, instance=INSTANCE)
        extra = h.get("extra", {})
        now = (h.get("processed"), h.get("dropped"), extra.get("scans_not_processed"))
        if h and extra.get("pending_inputs") == 0 and now == before:
            return waited
        before = now
        time.sleep(1.0)
    return timeout


def run_soak(args: argparse.Namespace) -> dict[str, Any]:
    """Start the service and the generator, sample until the end, stop, read the logs."""
    from service.live.sessions import client_config, free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-soak-"))
    env = {"RLUTF_RECORD_MAX_SECONDS": str(args.rotate_seconds)}
    heap = _HeapSnapshots(tmp / "heap", args.tracemalloc) if args.tracemalloc else None
    env.update(heap.env() if heap is not None else {})
    service_log = open(tmp / "service.log", "wb")  # noqa: SIM115 -- closed in finally
    flags = ("--processes", str(args.serve_processes)) if args.serve_processes else ()
    proc = start_service(
        endpoint, tmp, True, args.workers, serve_flags=flags, env=env, stderr=service_log
    )
    ctx = mp.get_context("spawn")
    out, requests, replies = ctx.Queue(), ctx.Queue(), ctx.Queue()
    ready, go, began, ended, finish = (ctx.Event() for _ in range(5))
    gen = ctx.Process(
        target=_generator,
        args=(
            endpoint,
            args.robots,
            args.minutes,
            args.loop_seconds,
            args.seed,
            out,
            ready,
            go,
            began,
            ended,
            requests,
            replies,
            finish,
        ),
    )
    samples: list[dict[str, Any]] = []
    try:
        import zenoh

        time.sleep(2.0)
        gen.start()
        deadline = time.monotonic() + 3600
        while not ready.wait(1.0):  # the generator draws its plans first
            if not gen.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(
                    f"the load generator did not get ready (exit code {gen.exitcode})"
                )
        session = zenoh.open(client_config(endpoint))
        go.set()
        began.wait(60)
        sampler = _Sampler(proc, gen, session, requests, replies)
        timeout = min(3.0, args.sample_s / 2)
        due = sampler.t0 + args.sample_s
        deadline = sampler.t0 + args.minutes * 60.0 + DRAIN_S + 240.0
        while not ended.wait(max(0.0, due - time.monotonic())):
            if proc.poll() is not None or not gen.is_alive():
                tail = (tmp / "service.log").read_text(errors="replace")[-3000:]
                raise RuntimeError(
                    f"stopped during the run: service exit code {proc.returncode}, load "
                    f"generator exit code {gen.exitcode}; the service's log ends:\n{tail}"
                )
            if time.monotonic() > deadline:
                raise RuntimeError("the load generator is stuck: the service does not read")
            samples.append(sampler.take(timeout))
            _progress(samples[-1])
            if heap is not None and not heap.taken and samples[-1]["minute"] >= args.warmup:
                heap.take(proc.pid)
            while due <= time.monotonic():
                due += args.sample_s
        cpu = sampler.cpu()
        if heap is not None:  # the end of the load, before the drain
            heap.take(proc.pid)
        drained = _wait_drained(session, timeout=DRAIN_S)
        time.sleep(1.0)  # the last poses on their way to the generator
        finish.set()
        result = out.get(timeout=120)
        health = query_health(session, instance=INSTANCE)
        requests.put(None)
        session.close()
        stop_code = stop_service(proc, timeout=120)
        gen.join(30)
        files, parts = check_logs(tmp / "logs")
        grew = heap.growth() if heap is not None else {}
    finally:
        if proc.poll() is None:
            stop_service(proc)
        service_log.close()
        if gen.is_alive():
            gen.terminate()
        shutil.rmtree(tmp, ignore_errors=True)
    return {
        "samples": samples,
        "generator": result,
        "health": health,
        "cpu": cpu,
        "files": files,
        "parts": parts,
        "stop_code": stop_code,
        "drained_s": drained,
        "heap": grew,
    }


def format_count(value: float) -> str:
    """A sampled count, ``-`` when it did not come (or the service does not report it)."""
    return "-" if isinstance(value, float) and math.isnan(value) else str(value)
