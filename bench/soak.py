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
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

from bench.fleetrun import layout_text, serve_layout
from bench.report import section_main
from bench.soakplan import (
    LONG_RUN_MINUTES,
    Verdict,
    counted_verdict,
    exit_code,
    logs_verdicts,
    memory_by_process,
    memory_verdict,
    outcome,
    overflow_verdict,
    queue_verdict,
    slope_per_10min,
)
from bench.soakrun import DRAIN_S, format_count, run_soak

SECTION = "soak"
PLOT = Path("docs/bench/soak.png")
OUT = Path("bench/out")


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
            max(1, args.serve_processes),
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


def _per_scan(cpu_s: float, scans: float) -> float:
    return 1e3 * cpu_s / scans if scans > 0 else math.nan


def _by_process(samples: list[dict[str, Any]], warmup: float) -> list[str]:
    table = memory_by_process(samples, warmup)
    if not table:
        return []
    return [
        "",
        "Where the service's memory is, per process (`host`: the process `rlutf serve` started, "
        "also the router and the map store; `p1`, ...: its other processes): each part from "
        f"the first sample after the {warmup:g} min warm-up to the last, MB, and its "
        "least-squares slope. `RssAnon` is the heap (Python objects, numpy arrays, Zenoh's "
        "buffers, malloc's free lists); `RssFile` the pages of mapped files (libraries, "
        "numba's compiled kernels) that the process has touched.",
        "",
        *table,
    ]


ROOT = Path(__file__).resolve().parent.parent  # the repository's paths are shown from here


def _heap(grew: dict[str, Any], warmup: float) -> list[str]:
    if not grew:
        return []
    lines = [
        "",
        "What grew in Python's allocations (`--tracemalloc`: every service process traced, a "
        f"snapshot after the {warmup:g} min warm-up and one at the end of the load), per process: "
        "the total, then the places that grew most (the allocation's innermost frame).",
        "",
        "| process | place | grew kB | blocks | kB at the end |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for label, g in grew.items():
        lines.append(f"| {label} | all traced | {g['total_kb']:+.0f} | | |")
        for r in g["rows"]:
            where = r["where"].split("site-packages/")[-1].replace(f"{ROOT}/", "")
            lines.append(
                f"| {label} | `{where}` | {r['kb']:+.1f} | {r['blocks']:+d} | {r['kb_after']:.0f} |"
            )
    return lines


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
            f"| {format_count(s['pending_inputs'])} | {format_count(s['recorder_queue'])} | {cpu} |"
        )
        prev = s
    return lines


def render(args: argparse.Namespace, into: list[Verdict]) -> str:
    """Run the soak and return the Markdown section; ``into`` receives the verdicts."""
    warmup = args.warmup_minutes
    if warmup is None:
        warmup = min(5.0, round(args.minutes / 3, 2))
    args.warmup = warmup  # the run's too (its tracemalloc snapshot)
    load = os.getloadavg()[0]
    run = run_soak(args)
    found = verdicts(run, args, warmup)
    into.extend(found)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    _save_series(run, OUT / f"soak-{stamp}")
    title = f"rlutf serve, {args.robots} robots at 10 Hz, recording rotated every "
    title += f"{args.rotate_seconds:g} s"
    figure = plot(run["samples"], warmup, title, PLOT if args.write else OUT / f"soak-{stamp}.png")
    s, g, h = run["samples"], run["generator"], run["health"]
    main, workers, gen = run["cpu"]
    rss = [x["rss_service_mb"] for x in s] or [math.nan]
    pss = [x["pss_service_mb"] for x in s] or [math.nan]
    grss = [x["rss_generator_mb"] for x in s] or [math.nan]
    files = run["files"]
    write = " --write" if args.write else ""
    lines = [
        f"Command: `python -m bench.soak --robots {args.robots} --minutes {args.minutes:g} "
        f"--rotate-seconds {args.rotate_seconds:g} --sample-s {args.sample_s:g} "
        f"--warmup-minutes {warmup:g} --loop-seconds {args.loop_seconds:g}"
        f"{'' if args.processes is None else f' --processes {args.processes}'}"
        f"{f' --tracemalloc {args.tracemalloc}' if args.tracemalloc else ''}{write}`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
        f"{platform.python_version()}. One `rlutf serve"
        f"{'' if args.processes is None else f' --processes {args.processes}'}` ("
        f"{layout_text(args.serve_processes)}; recording on, a new "
        "file every "
        f"{args.rotate_seconds:g} s) and one load-generator process share the cores: "
        f"{args.robots} robots at 10 Hz, 360-beam scans, 1 cm noise, each driving a "
        f"{args.loop_seconds:g} s loop (a path and back) with continuous drifting odometry, "
        f"for {args.minutes:g} min; sampled every {args.sample_s:g} s, warm-up "
        f"{warmup:g} min. Load average when the run started: {load:.1f}.",
        "",
        "| verdict | | figures |",
        "| --- | --- | --- |",
        *(f"| {v.name} | {outcome(v, args.minutes)} | {v.detail} |" for v in found),
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
        f"{slope_per_10min([x['minute'] for x in s], rss):+.2f} MB per 10 min; VmRSS added up "
        f"over its processes), its Pss (shared pages counted once) {pss[0]:.0f} / "
        f"{max(pss):.0f} / {pss[-1]:.0f} MB, generator "
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
        *_by_process(s, warmup),
        *_heap(run.get("heap", {}), warmup),
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
        "--rotate-seconds", type=float, default=60.0, help="seconds per log file (default 60)"
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
    p.add_argument(
        "--workers",
        type=int,
        help="service worker processes (the layout of workers; default: the service's layout)",
    )
    p.add_argument(
        "--processes",
        type=int,
        help="run `rlutf serve --processes N` (N service processes behind a host; 0: the "
        "layout of workers; default: the service's layout, `rlutf serve` with no flag)",
    )
    p.add_argument("--seed", type=int, default=7, help="random seed of the simulated fleet")
    p.add_argument(
        "--tracemalloc",
        type=int,
        default=0,
        metavar="FRAMES",
        help="trace Python's allocations in every service process (FRAMES frames each; costs "
        "CPU), snapshot them after the warm-up and at the end, and report what grew (default 0: "
        "off)",
    )
    p.add_argument(
        "--no-write",
        dest="write",
        action="store_false",
        default=False,
        help="only print (the default)",
    )
    judged: list[Verdict] = []
    minutes: list[float] = []

    def run(args: argparse.Namespace) -> str:
        minutes.append(args.minutes)
        # The layout run (``serve_processes``; 0: workers); ``processes`` stays as given, for
        # the command the section shows.
        args.workers, args.serve_processes = serve_layout(args.workers, args.processes)
        return render(args, judged)

    code = section_main(p, run, SECTION, argv) or exit_code(judged, minutes[0])
    for v in judged:
        said = outcome(v, minutes[0])
        if said == "FAIL":
            print(f"soak: {v.name}: FAIL ({v.detail})", file=sys.stderr)
        elif said != "pass":
            print(
                f"soak: {v.name}: not judged in a run under {LONG_RUN_MINUTES:g} min ({v.detail})",
                file=sys.stderr,
            )
    return code


if __name__ == "__main__":
    raise SystemExit(main())
