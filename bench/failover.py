"""Failover under load: ``kill -9`` of one process of ``rlutf serve --processes 2``.

Run: ``python -m bench.failover [--robots 200] [--kill-after 10] [--duration 30] [--write]``.

A ``rlutf serve --processes 2`` (the host, which is also the router and the map store, and
process 1; recording on) serves the load generator of :mod:`bench.restart` (odometry and a
360-beam scan at 10 Hz per robot). ``--kill-after`` seconds into the run, process 1 gets
SIGKILL, as the OOM killer would send it. Its robots go to the host, which has followed their
poses and odometry, and the host's supervisor starts process 1 again, after which the robots it
owns come back to it: two handovers for each of them.

Reported, from the poses the robots receive: the robots whose poses stopped at the kill (no
pose for more than :data:`GAP_S` across it), the time from the kill to each one's next pose
(the issue's target: within 2 s), the longest time any robot went without a pose across the
kill (every robot: the ones whose gap stayed under :data:`GAP_S` too), the longest gap of any
robot after that (the return to the restarted process), how far the first pose after each gap
is from the robot's true position then (target: within 5 cm), and the poses received twice for
the same robot and scan (two owners at once; target: none).
"""

from __future__ import annotations

import argparse
import itertools
import math
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from bench.fleetrun import start_service, stop_service
from bench.report import section_main
from bench.restart import generator, kill_header, kill_parser

SECTION = "failover"
#: A robot without a pose for longer than this, seconds, is between owners (10 Hz scans: the
#: usual gap is 0.1 s).
GAP_S = 0.5


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux ``/proc``)."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return found


def _serving_child(pid: int) -> int:
    """The host's child that is a service process (``python -m service serve ... --host-pid``)."""
    for child in children(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"serve" in cmd and b"--host-pid" in cmd:
            return child
    raise RuntimeError(f"rlutf serve {pid} has no service process as a child")


def measure(robots: int, duration: float, kill_after: float) -> dict[str, Any]:
    """One run: the host and its process, the generator, a kill; the raw times."""
    from service.live.sessions import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-failover-"))
    proc = start_service(endpoint, tmp, True, -1, serve_flags=("--processes", "2"))
    ctx = mp.get_context("spawn")
    out, ready, go = ctx.Queue(), ctx.Event(), ctx.Event()
    gen = ctx.Process(target=generator, args=(endpoint, robots, duration, out, ready, go, True))
    try:
        gen.start()
        ready.wait(600)
        go.set()
        time.sleep(kill_after)
        victim = _serving_child(proc.pid)
        killed = time.time_ns()
        os.kill(victim, signal.SIGKILL)
        result = out.get(timeout=duration + 120)
        gen.join(10)
    finally:
        if gen.is_alive():
            gen.terminate()
        stop_service(proc)
        shutil.rmtree(tmp, ignore_errors=True)
    return {**result, "killed": killed}


def figures(raw: dict[str, Any]) -> dict[str, Any]:
    """The robots moved at the kill, their time to a pose again, the gaps after, the errors."""
    killed, ids = raw["killed"], raw["ids"]
    gap_ns = int(GAP_S * 1e9)
    by_robot: dict[str, list[tuple[int, float]]] = {r: [] for r in ids}
    for robot, at, _stamp, off in raw["stamped"]:
        by_robot[robot].append((at, off))
    moved: list[float] = []  # seconds from the kill to the next pose (inf: none came)
    across: list[float] = []  # every robot's gap between its poses around the kill, seconds
    later: list[float] = []  # gaps after that one, seconds
    first_off: list[float] = []  # metres off, the first pose after each gap
    for arrivals in by_robot.values():
        arrivals.sort()
        if not arrivals or arrivals[-1][0] <= killed:
            moved.append(math.inf)  # no pose after the kill: never served again
        else:
            after = next(i for i, (at, _) in enumerate(arrivals) if at > killed)
            if after:
                across.append((arrivals[after][0] - arrivals[after - 1][0]) / 1e9)
        for (a, _), (b, off) in itertools.pairwise(arrivals):
            if b - a <= gap_ns or b <= killed:
                continue
            first_off.append(off)
            if a <= killed:
                moved.append((b - killed) / 1e9)
            else:
                later.append((b - a) / 1e9)
    twice = sum(1 for n in Counter((r, s) for r, _, s, _ in raw["stamped"]).values() if n > 1)
    return {
        "robots": len(ids),
        "scans": len(raw.get("puts", ())),
        "poses": len(raw["stamped"]),
        "moved": np.asarray(moved or [np.nan]),
        "moved_count": len(moved),
        "within_2s": sum(1 for s in moved if s <= 2.0),
        "across": max(across, default=math.nan),
        "later": np.asarray(later or [0.0]),
        "later_count": len(later),
        "off_cm": np.asarray(first_off or [np.nan]) * 100.0,
        "within_5cm": sum(1 for m in first_off if m <= 0.05),
        "gaps": len(first_off),
        "twice": twice,
    }


def render(args: argparse.Namespace) -> str:
    """Run once and return the section."""
    f = figures(measure(args.robots, args.duration, args.kill_after))

    def q(a: np.ndarray, p: float) -> str:
        return f"{float(np.nanpercentile(a, p)):.2f}" if not np.isnan(a).all() else "-"

    def most(a: np.ndarray) -> str:
        return f"{float(np.nanmax(a)):.2f}" if not np.isnan(a).all() else "-"

    return "\n".join(
        [
            *kill_header(
                "bench.failover",
                args,
                "one `rlutf serve --processes 2` (recording on)",
                f"SIGKILL of process 1 at {args.kill_after:g} s; the host starts it again. A "
                f"gap is more than {GAP_S:g} s without a pose.",
            ),
            "| robots | scans sent | poses received | robots whose poses stopped at the kill "
            "| kill to their next pose s: p50 / max | within 2 s | longest gap across the kill, "
            "any robot, s | later gaps (the return to process 1, and overload): count, longest s "
            "| first pose after a gap, cm off: p50 / max | within 5 cm | poses received twice "
            "for one scan |",
            "| ---: | ---: | ---: | ---: | --- | ---: | ---: | --- | --- | ---: | ---: |",
            f"| {f['robots']} | {f['scans']} | {f['poses']} | {f['moved_count']} "
            f"| {q(f['moved'], 50)} / {most(f['moved'])} "
            f"| {f['within_2s']} of {f['moved_count']} | {f['across']:.2f} "
            f"| {f['later_count']}, {float(np.max(f['later'])):.2f} "
            f"| {q(f['off_cm'], 50)} / {most(f['off_cm'])} "
            f"| {f['within_5cm']} of {f['gaps']} | {f['twice']} |",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    parser = kill_parser("python -m bench.failover", __doc__, 200)
    return section_main(parser, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
