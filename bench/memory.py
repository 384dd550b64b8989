"""Resident memory of ``rlutf serve``, process by process: idle, under a fleet, after it (issue 21).

Run: ``python -m bench.memory [--robots 50,100] [--duration 20] [--workers 0] [--write]``.

For each fleet size, a fresh ``rlutf serve`` subprocess (router on a loopback port, embedded
store, recording on unless ``--no-record``) is measured in three phases: idle (``--settle``
seconds after it is ready, no robot yet), under the load generator of :mod:`bench.fleet`
(every robot odometry and a 360-beam scan at 10 Hz for ``--duration`` seconds; sampled every
second, the peak and the last sample kept) and after it (``--settle`` seconds after the
generator stopped). For every process of the service (the ``rlutf serve`` process and its
descendants: worker processes, the processes of ``--processes N`` and theirs, the map validator
while it runs) Linux's own counters
(:mod:`bench.procstat`): ``VmRSS`` (resident: what ``top`` shows), of it ``RssAnon`` (the
process's own heap) and ``RssFile`` (pages of mapped files, mostly shared libraries: the same
library file mapped by several processes is in memory once), and ``Pss`` from
``/proc/PID/smaps_rollup`` (each shared page divided among the processes mapping it: the sum
of ``Pss`` over all processes is what they take from the machine together).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from bench.fleetrun import fleet_generator, health, start_service, stop_service
from bench.procstat import MEMORY_PARTS, descendants, process_memory_mb
from bench.report import ints_text, section_main

SECTION = "memory"
FIELDS = MEMORY_PARTS

Sample = dict[int, dict[str, float]]
"""Memory of each process of the service by pid: :func:`bench.procstat.process_memory_mb`."""


def sample_tree(pid: int) -> Sample:
    """The memory of ``pid`` and each of its descendants (processes gone meanwhile left out)."""
    found = {}
    for p in [pid, *descendants(pid)]:
        m = process_memory_mb(p)
        if m is not None:
            found[p] = m
    return found


def totals(sample: Sample, main: int) -> dict[str, dict[str, float]]:
    """``main`` (the ``rlutf serve`` process), ``children`` (summed) and ``all``, by field."""
    kids = [m for p, m in sample.items() if p != main]
    out = {
        "main": sample.get(main, dict.fromkeys(FIELDS, float("nan"))),
        "children": {f: sum(m[f] for m in kids) for f in FIELDS},
        "all": {f: sum(m[f] for m in sample.values()) for f in FIELDS},
    }
    out["children"]["count"] = len(kids)
    return out


def run_size(
    robots: int, duration: float, record: bool, workers: int, settle: float, processes: int = 0
) -> dict[str, Any]:
    """One fresh service: idle, under ``robots`` robots for ``duration`` s, and after."""
    from service.live.sessions import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-memory-"))
    flags = ("--processes", str(processes)) if processes else ()
    proc = start_service(endpoint, tmp, record, workers, flags, instance="memorybench")
    ctx = mp.get_context("spawn")
    out, ready, go, began, ended = ctx.Queue(), ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    gen = ctx.Process(
        target=fleet_generator,
        args=(endpoint, robots, duration, "json", out, ready, go, began, ended),
    )
    loaded: list[Sample] = []
    stop = threading.Event()
    try:
        time.sleep(settle)
        idle = sample_tree(proc.pid)
        result = {"scans_sent": 0, "poses": 0}
        if robots:
            gen.start()
            ready.wait(600)
            go.set()
            began.wait(60)

            def sample() -> None:
                while not stop.wait(1.0):
                    loaded.append(sample_tree(proc.pid))

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            ended.wait(duration + 120)
            stop.set()
            sampler.join()
            result = out.get(timeout=60)
            gen.join(10)
        else:
            time.sleep(duration)
        time.sleep(settle)
        after = sample_tree(proc.pid)
        h = health(endpoint)
    finally:
        stop.set()
        stop_service(proc)
        shutil.rmtree(tmp, ignore_errors=True)
    peak = max(loaded, key=lambda s: totals(s, proc.pid)["all"]["rss"]) if loaded else idle
    return {
        "robots": robots,
        "idle": totals(idle, proc.pid),
        "peak": totals(peak, proc.pid),
        "last": totals(loaded[-1] if loaded else idle, proc.pid),
        "after": totals(after, proc.pid),
        "sent": result["scans_sent"],
        "poses": result["poses"],
        "processed": int(h.get("processed", -1)),
    }


def _cell(m: dict[str, float]) -> str:
    return f"{m['rss']:.0f} ({m['anon']:.0f} + {m['file']:.0f}) / {m['pss']:.0f}"


def render_rows(r: dict[str, Any]) -> list[str]:
    """Markdown rows of one size: a row per phase."""
    rows = []
    for phase, label in (("idle", "idle"), ("peak", "peak"), ("last", "end of load")):
        if phase == "idle" or r["robots"]:
            t = r[phase]
            rows.append(
                f"| {r['robots']} | {label} | {_cell(t['main'])} "
                f"| {int(t['children']['count'])}: {_cell(t['children'])} | {_cell(t['all'])} |"
            )
    t = r["after"]
    rows.append(
        f"| {r['robots']} | {settle_label(r)} | {_cell(t['main'])} "
        f"| {int(t['children']['count'])}: {_cell(t['children'])} | {_cell(t['all'])} |"
    )
    return rows


def settle_label(r: dict[str, Any]) -> str:
    """The label of the phase after the load."""
    return "after (robots gone)" if r["robots"] else "idle, later"


def render(args: argparse.Namespace) -> str:
    """Run every size and return the Markdown section."""
    sizes = [int(s) for s in args.robots.split(",")]
    load = os.getloadavg()[0]
    rows: list[str] = []
    runs = []
    for n in sizes:
        r = run_size(
            n, args.duration, not args.no_record, args.workers, args.settle, args.processes
        )
        runs.append(r)
        rows += render_rows(r)
        print("\n".join(render_rows(r)), flush=True)
    flags = " --no-record" if args.no_record else ""
    flags += f" --processes {args.processes}" if args.processes else ""
    return "\n".join(
        [
            f"Command: `python -m bench.memory --robots {args.robots} --duration "
            f"{args.duration:g} --workers {args.workers} --settle {args.settle:g}{flags} "
            "--write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}; load average when the run started: {load:.1f}. "
            f"A fresh `rlutf serve --workers {args.workers}{flags}` per fleet size (recording "
            f"{'off' if args.no_record else 'on'}), measured {args.settle:g} s after it is "
            f"ready (idle), every second of {args.duration:g} s of 10 Hz scans and odometry "
            f"(peak: the sample of most resident memory in total; end of load: the last "
            f"sample) and {args.settle:g} s after the fleet stopped. Each cell: resident MB "
            "(`VmRSS`) with, in brackets, its anonymous + file-backed parts (`RssAnon` + "
            "`RssFile`), then `Pss` (shared pages divided among the processes that map them; "
            "the sum of `Pss` is what the processes take from the machine together).",
            "",
            "| robots | phase | `rlutf serve` process MB | descendants: count: MB | all MB |",
            "| ---: | --- | --- | --- | --- |",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.memory",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--robots",
        type=ints_text(0),
        default="50,100",
        help="fleet sizes, comma-separated (0: idle)",
    )
    p.add_argument("--duration", type=float, default=20.0, help="seconds of load per size")
    p.add_argument("--workers", type=int, default=0, help="service worker processes (default 0)")
    p.add_argument(
        "--settle", type=float, default=10.0, help="seconds before the idle and after samples"
    )
    p.add_argument(
        "--processes", type=int, default=0, help="rlutf serve --processes N (default 0: none)"
    )
    p.add_argument("--no-record", action="store_true", help="service without MCAP recording")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
