"""Soak: one service instance under a fleet's load for a long time, recording with rotation
(issue 15).

Run: ``python -m bench.soak [--robots 100] [--minutes 30] [--rotate-seconds 60] [--sample-s 10]
[--warmup-minutes N] [--write | --no-write]``.

A ``rlutf serve`` subprocess (router on a loopback port, embedded store, worker processes,
recording on with a new file every ``--rotate-seconds``: ``RLUTF_RECORD_MAX_SECONDS``) serves a
load-generator process that publishes, for every robot, odometry and a 360-beam scan at 10 Hz,
as :mod:`bench.fleet` does. A run this long cannot be precomputed: each robot drives a loop of
``--loop-seconds`` (a path forward, then back to its start), its scans simulated once per pose
and its odometry accumulated from the loop's drifting increments, one continuous stream however
many loops it drives (:mod:`bench.soakplan`).

Every ``--sample-s`` seconds: the service's resident memory (main process and workers) and CPU
time (main, workers; the generator's too), its health (received, processed, dropped, pending
inputs, recorder queue and overflow, scans not processed), and from the generator the scans
sent, poses received and the scan-to-pose latency p50 and p99 over the interval; a progress
line goes to stderr and the series to ``bench/out/soak-*.csv`` (and ``.json``).

Verdicts: the memory slope after ``--warmup-minutes`` (least-squares fit, at most 1 MB per 10
minutes); no queue that grows (pending inputs and the recorder queue: the last third's median not
above the first third's max by more than a margin, one message per robot for pending inputs, ten
for the recorder; the recorder never overflowing); every scan answered or counted (sent = poses
received + dropped + not processed, as the service reports them, read once it has drained: no
input pending, counts settled); and, after an orderly stop (SIGTERM), the logs: rotated (at
least one file per ``--rotate-seconds`` of the run), no ``.mcap.part`` left, every file read end
to end with the service's own reader, and their pose messages summing to the poses published
(less what the recorder reported not recorded).

Exit code 1 when the scans are not all counted or the logs fail a verdict; the memory and queue
verdicts count toward it only on runs of 10 minutes or more, where their targets apply (on a
short run on a shared machine they are printed, not judged). ``--write`` updates the ``soak``
section of BENCHMARKS.md and ``docs/bench/soak.png``; without it the plot goes to ``bench/out/``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing as mp
import os
import platform
import queue
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.fleet import (
    RATE_HZ,
    _children,
    _cpu_seconds,
    _rss_tree_mb,
    open_fleet,
    query_health,
    start_service,
    stop_service,
    timed_publishing,
)
from bench.report import section_main
from bench.soakplan import (
    FileCheck,
    LatencyHistogram,
    OdometryStream,
    Verdict,
    counted_verdict,
    exit_code,
    logs_verdicts,
    make_loop,
    memory_verdict,
    overflow_verdict,
    queue_verdict,
    slope_per_10min,
)

SECTION = "soak"
PLOT = Path("docs/bench/soak.png")
OUT = Path("bench/out")
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

    from rlutf.sim import (
        LidarModel,
        OdometryModel,
        make_building,
        make_trajectory,
        simulate_scan,
    )

    rng = np.random.default_rng(seed)
    world = make_building(rng)
    forward = max(2, round(loop_seconds * RATE_HZ / 2) + 1)
    lidar = LidarModel(beams=360)
    rids, loops, tails = [], [], []
    for i in range(robots):
        loop = make_loop(
            make_trajectory(world, rng, forward, dt=1.0 / RATE_HZ), OdometryModel(), rng
        )
        scans = []
        for pose in loop.truth[:forward]:
            s = simulate_scan(world, pose, lidar, rng)
            ranges = [round(float(r), 4) if math.isfinite(r) else None for r in s.ranges]
            scans.append(
                json.dumps(
                    {
                        "angle_min": s.angle_min,
                        "angle_increment": s.angle_increment,
                        "range_min": s.range_min,
                        "range_max": s.range_max,
                        "ranges": ranges,
                    }
                )[1:]
            )
        rids.append(f"r{i:03d}")
        loops.append(loop)
        tails.append([scans[j] for j in loop.scan_of_step])  # references, one per loop step
    streams = [OdometryStream(loop.truth[0], loop.increments) for loop in loops]

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

    starts = [
        (rid, stream.pose, loop.truth[0])
        for rid, stream, loop in zip(rids, streams, loops, strict=True)
    ]
    # Blocking publishers: a scan the generator's own transport dropped (Zenoh's default when
    # its queue is full, as on two starved cores) would be counted by no one; blocked, the
    # generator falls behind its schedule instead, and says so.
    sessions, sub, pubs, t0 = open_fleet(
        endpoint, world, starts, on_pose, congestion_control=zenoh.CongestionControl.BLOCK
    )
    threading.Thread(target=answer, daemon=True).start()

    def send(i: int, k: int, stamp: int) -> None:
        x, y, th = streams[i].advance()  # step k + 1
        head = f'{{"stamp_ns": {stamp}, '
        pubs[i][0].put(f'{head}"x": {x!r}, "y": {y!r}, "theta": {th!r}}}')
        with lock:
            sent[(rids[i], stamp)] = time.time_ns()
            counts["sent"] += 1
        pubs[i][1].put(head + tails[i][(k + 1) % len(tails[i])])

    steps = int(minutes * 60 * RATE_HZ) + 1
    scans_sent, behind, cpu = timed_publishing(robots, steps, t0, send, ready, go, began, ended)
    finish.wait(120)
    last = figures()
    sub.undeclare()
    for s in sessions:
        s.close()
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
        self.requests, self.replies = requests, replies
        self.t0 = time.monotonic()
        self.main0 = _cpu_seconds(proc.pid)
        self.workers: dict[int, float] = {p: _cpu_seconds(p) for p in _children(proc.pid)}
        self.workers0 = sum(self.workers.values())
        self.gen0 = _cpu_seconds(gen.pid)
        self.n = 0

    def cpu(self) -> tuple[float, float, float]:
        """CPU seconds since the start: service main, its workers (each as last seen), generator."""
        for p in _children(self.proc.pid):
            c = _cpu_seconds(p)
            if math.isfinite(c):
                self.workers[p] = c
        return (
            _cpu_seconds(self.proc.pid) - self.main0,
            sum(self.workers.values()) - self.workers0,
            _cpu_seconds(self.gen.pid) - self.gen0,
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

    def take(self, timeout: float) -> dict[str, Any]:
        """One sample (see the module docstring); ``nan`` where a figure did not come."""
        minute = (time.monotonic() - self.t0) / 60.0
        main, workers, gen_cpu = self.cpu()
        h = query_health(self.session, timeout=timeout)
        extra = h.get("extra", {})
        g = self._generator_figures(timeout)
        lat = h.get("latency_ms", {})
        nan = math.nan
        return {
            "minute": minute,
            "rss_service_mb": _rss_tree_mb(self.proc.pid),
            "rss_generator_mb": _rss_tree_mb(self.gen.pid),
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


def check_logs(record_dir: Path) -> tuple[list[FileCheck], list[str]]:
    """Every finished log file read end to end, and the names of ``.part`` files left."""
    from schemas import SCHEMA_NAMES, PoseEstimate
    from service.logs.mcapread import LogError, LogFile

    pose_schema = SCHEMA_NAMES[PoseEstimate]
    checks = []
    for path in sorted(record_dir.glob("*.mcap")):
        messages = poses = indexed = 0
        first, last = math.inf, -math.inf
        error = None
        try:
            with LogFile(path) as log:
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
            FileCheck(path.name, path.stat().st_size, messages, indexed, poses, span, error)
        )
    return checks, sorted(p.name for p in record_dir.glob("*.part"))


def _progress(s: dict[str, Any]) -> None:
    print(
        f"[soak {s['minute']:5.1f} min] service {s['rss_service_mb']:.0f} MB, generator "
        f"{s['rss_generator_mb']:.0f} MB; sent {s['sent']}, poses {s['poses']}, dropped "
        f"{s['dropped']}, not processed {s['not_processed']}; latency p50 "
        f"{s['latency_p50_ms']:.1f} p99 {s['latency_p99_ms']:.1f} ms; pending "
        f"{_count(s['pending_inputs'])}, recorder queue {_count(s['recorder_queue'])}, overflow "
        f"{s['recorder_overflow']}",
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
        h = query_health(session, timeout=2.0)
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
    proc = start_service(endpoint, tmp, True, args.workers, env=env)
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
        if not ready.wait(3600):
            raise RuntimeError("the load generator did not get ready")
        session = zenoh.open(client_config(endpoint))
        go.set()
        began.wait(60)
        sampler = _Sampler(proc, gen, session, requests, replies)
        timeout = min(3.0, args.sample_s / 2)
        due = sampler.t0 + args.sample_s
        deadline = sampler.t0 + args.minutes * 60.0 + DRAIN_S + 240.0
        while not ended.wait(max(0.0, due - time.monotonic())):
            if proc.poll() is not None or not gen.is_alive():
                raise RuntimeError("the service or the load generator stopped during the run")
            if time.monotonic() > deadline:
                raise RuntimeError("the load generator is stuck: the service does not read")
            samples.append(sampler.take(timeout))
            _progress(samples[-1])
            while due <= time.monotonic():
                due += args.sample_s
        cpu = sampler.cpu()
        drained = _wait_drained(session, timeout=DRAIN_S)
        time.sleep(1.0)  # the last poses on their way to the generator
        finish.set()
        result = out.get(timeout=120)
        health = query_health(session)
        requests.put(None)
        session.close()
        stop_code = stop_service(proc, timeout=120)
        gen.join(30)
        files, parts = check_logs(tmp / "logs")
    finally:
        if proc.poll() is None:
            stop_service(proc)
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
    }


def verdicts(run: dict[str, Any], args: argparse.Namespace, warmup: float) -> list[Verdict]:
    """Every verdict of a run (see the module docstring)."""
    s, h, g = run["samples"], run["health"], run["generator"]
    t = [x["minute"] for x in s]
    extra = h.get("extra", {})
    overflow = int(extra.get("recorder_overflow", 0))
    return [
        memory_verdict(t, [x["rss_service_mb"] for x in s], warmup),
        queue_verdict("pending inputs", t, [x["pending_inputs"] for x in s], warmup, args.robots),
        queue_verdict(
            "recorder queue", t, [x["recorder_queue"] for x in s], warmup, 10 * args.robots
        ),
        overflow_verdict(t, [x["recorder_overflow"] for x in s], warmup),
        counted_verdict(
            g["scans_sent"],
            g["poses"],
            int(h.get("dropped", -1)),
            int(extra.get("scans_not_processed", 0)),
        ),
        *logs_verdicts(
            run["files"],
            run["parts"],
            args.minutes * 60.0,
            args.rotate_seconds,
            int(h.get("processed", -1)),
            overflow,
        ),
    ]


def plot(samples: list[dict[str, Any]], warmup: float, title: str, path: Path) -> Path:
    """Memory and latency over time, two panels (matplotlib, Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t = [s["minute"] for s in samples]
    fig = Figure(figsize=(8, 6), layout="constrained")
    mem, lat = fig.subplots(2, 1, sharex=True)
    mem.plot(t, [s["rss_service_mb"] for s in samples], label="service (main + workers)")
    mem.set_ylabel("service resident memory, MB")
    other = mem.twinx()  # its own scale: one axis for both would flatten the service's line
    other.plot(t, [s["rss_generator_mb"] for s in samples], color="0.5", ls="--")
    other.set_ylabel("load generator (dashed), MB", color="0.4")
    lat.plot(t, [s["latency_p50_ms"] for s in samples], label="p50")
    lat.plot(t, [s["latency_p99_ms"] for s in samples], label="p99")
    lat.set_ylabel("scan to pose, ms")
    lat.set_yscale("log")
    lat.set_xlabel("minutes")
    for ax in (mem, lat):
        ax.axvspan(0, warmup, color="0.9", label="warm-up")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    mem.set_title(title, fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100)
    return path


def _save_series(run: dict[str, Any], stem: Path) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    with open(stem.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(run["samples"][0]) if run["samples"] else [])
        writer.writeheader()
        writer.writerows(run["samples"])
    summary = {k: v for k, v in run.items() if k != "files"}
    summary["files"] = [f._asdict() for f in run["files"]]
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=1, default=str))


def _count(value: float) -> str:
    """A sampled count, ``-`` when it did not come (or the service does not report it)."""
    return "-" if isinstance(value, float) and math.isnan(value) else str(value)


def _per_scan(cpu_s: float, scans: float) -> float:
    return 1e3 * cpu_s / scans if scans > 0 else math.nan


def _table(samples: list[dict[str, Any]], rows: int = 10) -> list[str]:
    """Every few samples (about ``rows`` rows and the last), CPU per scan since the row above."""
    stride = max(1, math.ceil(len(samples) / rows))
    picked = samples[stride - 1 :: stride]
    if samples and picked[-1] is not samples[-1]:
        picked.append(samples[-1])
    lines = [
        "| minute | service RSS MB | scans sent | poses | dropped | p50 ms | p99 ms "
        "| pending inputs | recorder queue | CPU ms per scan since the row above: main / workers "
        "/ generator |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    prev = {"sent": 0, "cpu_main_s": 0.0, "cpu_workers_s": 0.0, "cpu_generator_s": 0.0}
    for s in picked:
        n = s["sent"] - prev["sent"]
        cpu = " / ".join(
            f"{_per_scan(s[k] - prev[k], n):.2f}"
            for k in ("cpu_main_s", "cpu_workers_s", "cpu_generator_s")
        )
        lines.append(
            f"| {s['minute']:.1f} | {s['rss_service_mb']:.0f} | {s['sent']} | {s['poses']} "
            f"| {s['dropped']} | {s['latency_p50_ms']:.1f} | {s['latency_p99_ms']:.1f} "
            f"| {_count(s['pending_inputs'])} | {_count(s['recorder_queue'])} | {cpu} |"
        )
        prev = s
    return lines


def render(args: argparse.Namespace, outcome: list[Verdict]) -> str:
    """Run the soak and return the Markdown section; ``outcome`` receives the verdicts."""
    warmup = args.warmup_minutes
    if warmup is None:
        warmup = min(5.0, round(args.minutes / 3, 2))
    load = os.getloadavg()[0]
    run = run_soak(args)
    found = verdicts(run, args, warmup)
    outcome.extend(found)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    _save_series(run, OUT / f"soak-{stamp}")
    title = f"rlutf serve, {args.robots} robots at 10 Hz, recording rotated every "
    title += f"{args.rotate_seconds:g} s"
    figure = plot(run["samples"], warmup, title, PLOT if args.write else OUT / f"soak-{stamp}.png")
    s, g, h = run["samples"], run["generator"], run["health"]
    main, workers, gen = run["cpu"]
    rss = [x["rss_service_mb"] for x in s] or [math.nan]
    grss = [x["rss_generator_mb"] for x in s] or [math.nan]
    files = run["files"]
    write = " --write" if args.write else ""
    lines = [
        f"Command: `python -m bench.soak --robots {args.robots} --minutes {args.minutes:g} "
        f"--rotate-seconds {args.rotate_seconds:g} --sample-s {args.sample_s:g} "
        f"--warmup-minutes {warmup:g} --loop-seconds {args.loop_seconds:g}{write}`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
        f"{platform.python_version()}. One `rlutf serve` (recording on, a new file every "
        f"{args.rotate_seconds:g} s) and one load-generator process share the cores: "
        f"{args.robots} robots at 10 Hz, 360-beam scans, 1 cm noise, each driving a "
        f"{args.loop_seconds:g} s loop (a path and back) with continuous drifting odometry, "
        f"for {args.minutes:g} min; sampled every {args.sample_s:g} s, warm-up "
        f"{warmup:g} min. Load average when the run started: {load:.1f}.",
        "",
        "| verdict | | figures |",
        "| --- | --- | --- |",
        *(f"| {v.name} | {'pass' if v.ok else 'FAIL'} | {v.detail} |" for v in found),
        "",
        f"Over the run: {g['scans_sent']} scans sent, {g['poses']} poses received, "
        f"{h.get('dropped')} dropped and {h.get('extra', {}).get('scans_not_processed')} not "
        f"processed (reported); scan to pose p50 {g['p50']:.1f} ms, p99 {g['p99']:.1f} ms, "
        f"max {g['max']:.0f} ms; CPU ms per scan sent: service main / workers / generator "
        f"{_per_scan(main, g['scans_sent']):.2f} / {_per_scan(workers, g['scans_sent']):.2f} / "
        f"{_per_scan(gen, g['scans_sent']):.2f}; inputs the service received: "
        f"{h.get('received')} of {2 * g['scans_sent'] + 2 * args.robots} sent (scans, "
        "odometry, initial poses); service RSS first / peak / last "
        f"{rss[0]:.0f} / {max(rss):.0f} / {rss[-1]:.0f} MB (slope over the whole run "
        f"{slope_per_10min([x['minute'] for x in s], rss):+.2f} MB per 10 min), generator "
        f"{grss[0]:.0f} / {max(grss):.0f} / {grss[-1]:.0f} MB; the generator ended "
        f"{g['behind_s']:.2f} s behind its schedule; "
        + (
            f"the service had drained (no input pending, counts settled) "
            f"{run['drained_s']:.1f} s after the last scan."
            if run["drained_s"] < DRAIN_S
            else f"the service had not drained {DRAIN_S:g} s after the last scan."
        ),
        "",
        f"Logs: {len(files)} files, {sum(f.size_bytes for f in files) / 1e6:.0f} MB, "
        f"{sum(f.messages for f in files)} messages read end to end with "
        "`service.logs.mcapread`; the service stopped on SIGTERM "
        + (f"with exit code {run['stop_code']}." if run["stop_code"] is not None else "(killed).")
        + " Each row of the table below is one sample; latency is over its interval.",
        "",
        f"![Soak: memory and latency over time]({figure.as_posix()})"
        if args.write
        else f"Plot: `{figure.as_posix()}` (not committed).",
        "",
        *_table(s),
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.soak",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=100, help="fleet size (default 100)")
    p.add_argument("--minutes", type=float, default=30.0, help="length of the run (default 30)")
    p.add_argument(
        "--rotate-seconds", type=float, default=60.0, help="a new log file every (default 60)"
    )
    p.add_argument("--sample-s", type=float, default=10.0, help="sampling period (default 10)")
    p.add_argument(
        "--warmup-minutes",
        type=float,
        default=None,
        help="samples before this are left out of the slope and queue verdicts (default: "
        "5, or a third of a shorter run)",
    )
    p.add_argument(
        "--loop-seconds",
        type=float,
        default=30.0,
        help="each robot's loop, there and back (default 30; its scans are precomputed)",
    )
    p.add_argument("--workers", type=int, default=-1, help="service worker processes")
    p.add_argument("--seed", type=int, default=7, help="random seed of the simulated fleet")
    p.add_argument(
        "--no-write",
        dest="write",
        action="store_false",
        default=False,
        help="only print (the default)",
    )
    outcome: list[Verdict] = []
    minutes: list[float] = []

    def run(args: argparse.Namespace) -> str:
        minutes.append(args.minutes)
        return render(args, outcome)

    code = section_main(p, run, SECTION, argv) or exit_code(outcome, minutes[0])
    for v in outcome:
        if not v.ok:
            print(f"soak: {v.name}: FAIL ({v.detail})", file=sys.stderr)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
