"""What the MCAP recorder costs per scan: CPU of the service's main process, and bytes on disk.

Run: ``python -m bench.recorder [--robots 50] [--seconds 10] [--rate 2000] [--levels=1,3]``.

The live service records, per scan of a robot, its odometry (bench.fleet's robots send one
reading before each scan), the 360-beam LaserScan and the PoseEstimate it answered with; the
recorder (:class:`service.logs.mcaplog.McapRecorder`) queues them on the thread that handled
them and writes them on its own thread. This feeds it those three records per scan, made the
way the fleet benchmark's robots and the service make them (:mod:`service.sim.wire`'s JSON,
:func:`schemas.fastpose.encode_pose`), at ``--rate`` scans a second of wall time (paced, so the
writer thread runs in batches as in the service), and reports the process CPU per scan (the
callers' ``record`` and the writer thread together: both hold the main process's GIL), the
part of it on the writer thread, and the file size per scan, for each variant: the WIRE.md
channels alone (the default) and with the Foxglove views (``record_views``), and the zstd
levels and chunk sizes given.
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.report import ints_text
from schemas.fastpose import encode_pose
from service.keys import Keys
from service.logs.mcaplog import McapRecorder
from service.sim.plan import FleetSpec, plan_fleet
from service.sim.wire import JsonWire

#: zstd's fastest level (its negative levels trade ratio for speed).
ZSTD_MIN_LEVEL = -131072
SCAN = "rlutf.LaserScan"
ODOM = "rlutf.Odometry"
POSE = "rlutf.PoseEstimate"
#: The scans fed between two pauses of the pacing loop.
BURST = 20


@dataclass(frozen=True)
class Variant:
    """One recorder configuration."""

    views: bool
    level: int | None = None  # None: the recorder's default
    chunk_size: int | None = None

    @property
    def label(self) -> str:
        text = "WIRE channels + Foxglove views" if self.views else "WIRE channels"
        if self.level is not None:
            text += f", zstd level {self.level}"
        if self.chunk_size is not None:
            text += f", chunks {self.chunk_size // 1024} KiB"
        return text

    def options(self) -> dict[str, Any]:
        """The recorder's keyword arguments."""
        out: dict[str, Any] = {"foxglove": self.views}
        if self.level is not None:
            out["zstd_level"] = self.level
        if self.chunk_size is not None:
            out["chunk_size"] = self.chunk_size
        return out


@dataclass(frozen=True)
class Outcome:
    """What one variant cost."""

    variant: Variant
    scans: int
    messages: int
    cpu_us: float  # per scan, the whole process
    writer_us: float  # per scan, the writer thread
    bytes_per_scan: float
    overflowed: int


def records(robots: int, scans: int) -> Iterator[tuple[str, str, bytes, int, int]]:
    """``(topic, schema, payload, log_time, publish_time)``: odometry, scan and pose per scan."""
    steps = -(-scans // robots)
    spec = FleetSpec(robots=robots, poses=steps + 1, seed=3)  # no scan twice
    plan = plan_fleet(spec)
    wire = JsonWire(plan)
    keys = Keys()
    ids = spec.ids
    t0 = 1_800_000_000_000_000_000
    period = spec.period_ns
    n = 0
    step = 0
    while True:
        for i, rid in enumerate(ids):
            if n >= scans:
                return
            stamp = t0 + step * period + i * 1000
            at = stamp + 500_000
            yield keys.robot(rid, "odom"), ODOM, wire.odometry(i, step, stamp), at, stamp
            yield keys.robot(rid, "scan"), SCAN, wire.scan(i, step, stamp), at + 1, stamp
            x, y = 1.0 + 0.01 * step + 0.1 * i, 2.0 + 0.003 * step
            theta = math.fmod(0.01 * step + i, math.pi)
            cov = (1e-4 + 1e-6 * i, 1e-6, 0.0, 1e-6, 1.2e-4, 0.0, 0.0, 0.0, 3e-5)
            pose = encode_pose(
                stamp, rid, "sim", x, y, theta, "tracking", 0.0123, 7, cov, None, 0.93, 0.02
            )
            yield keys.robot(rid, "pose"), POSE, pose, at + 900_000, stamp
            n += 1
        step += 1


def _thread_cpu(thread: threading.Thread) -> float:
    ident = thread.ident
    if ident is None:
        return 0.0
    return time.clock_gettime(time.pthread_getcpuclockid(ident))


Feed = list[tuple[str, str, bytes, int, int]]


def run(variant: Variant, feed: Feed, rate: float, folder: Path) -> Outcome:
    """Feed the records at ``rate`` scans a second; measure the recorder."""
    scans = len(feed) // 3
    rec = McapRecorder(
        folder,
        queue_size=len(feed) + 10,
        flush_interval_s=1.0,
        **variant.options(),
    )
    writer = rec._thread
    rec.set_config({"prefix": "rlutf"})
    time.sleep(0.1)
    cpu0, writer0 = time.process_time(), _thread_cpu(writer)
    start = time.monotonic()
    per_burst = 3 * BURST
    record = rec.record
    for b in range(0, len(feed), per_burst):
        for item in feed[b : b + per_burst]:
            record(*item)
        ahead = start + (b // 3 + BURST) / rate - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    while rec.queued:
        time.sleep(0.01)
    writer1 = _thread_cpu(writer)
    rec.close()
    cpu1 = time.process_time()
    size = sum(p.stat().st_size for p in rec.files)
    messages = len(feed)
    return Outcome(
        variant,
        scans,
        messages,
        (cpu1 - cpu0) / scans * 1e6,
        (writer1 - writer0) / scans * 1e6,
        size / scans,
        rec.overflowed,
    )


def render(outcomes: list[Outcome], command: str, robots: int, rate: float, repeat: int) -> str:
    """The results as Markdown."""
    lines = [
        f"Command: `{command}`",
        "",
        f"Machine: {platform.machine()}, CPython {platform.python_version()}. "
        f"{robots} robots' records (odometry, 360-beam scan, pose per scan) fed to one "
        f"McapRecorder at {rate:g} scans a second; CPU of the whole process per scan (the "
        "callers' `record` and the writer thread), of the writer thread alone, and the finished "
        "file's bytes per scan; the median of "
        f"{repeat} runs per row.",
        "",
        "| recorder | scans | CPU us per scan: process / writer thread | bytes per scan | "
        "not recorded |",
        "| --- | ---: | --- | ---: | ---: |",
    ]
    lines += [
        f"| {o.variant.label} | {o.scans} | {o.cpu_us:.1f} / {o.writer_us:.1f} | "
        f"{o.bytes_per_scan:,.0f} | {o.overflowed} |"
        for o in outcomes
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.recorder", description=__doc__)
    p.add_argument("--robots", type=int, default=50, help="robots (topics) recorded")
    p.add_argument("--seconds", type=float, default=10.0, help="log time at 10 Hz per robot")
    p.add_argument("--rate", type=float, default=2000.0, help="scans fed per second")
    p.add_argument(
        "--levels",
        type=ints_text(ZSTD_MIN_LEVEL, empty=True),
        default="",
        help="zstd levels to compare, e.g. 1,3",
    )
    p.add_argument(
        "--chunks",
        type=ints_text(1, empty=True),
        default="",
        help="chunk sizes to compare, KiB, e.g. 256,1024",
    )
    p.add_argument("--no-views", action="store_true", help="leave out the views variant")
    p.add_argument("--repeat", type=int, default=3, help="runs per variant (the median is shown)")
    args = p.parse_args(argv)
    scans = round(args.robots * 10 * args.seconds)
    variants = [Variant(False)]
    if not args.no_views:
        variants.append(Variant(True))
    variants += [Variant(False, level=int(x)) for x in filter(None, args.levels.split(","))]
    variants += [
        Variant(False, chunk_size=int(x) * 1024) for x in filter(None, args.chunks.split(","))
    ]
    feed = list(records(args.robots, scans))  # made before any clock starts
    with tempfile.TemporaryDirectory() as tmp:  # warm up: imports, caches, the first file
        run(Variant(False), feed[: len(feed) // 10], args.rate, Path(tmp))
    outcomes = []
    for v in variants:
        runs = []
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory() as tmp:
                runs.append(run(v, feed, args.rate, Path(tmp)))
        outcomes.append(sorted(runs, key=lambda o: o.cpu_us)[len(runs) // 2])
    command = "python -m bench.recorder " + " ".join(sys.argv[1:] if argv is None else argv)
    print(render(outcomes, command.strip(), args.robots, args.rate, args.repeat))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
