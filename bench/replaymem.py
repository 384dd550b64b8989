"""Replay's memory against the length of the log it audits.

Run: ``python -m bench.replaymem [--robots 20] [--steps 300,600,1200,2400] [--write]``.

An audit replays a whole run, and a service runs for weeks: a day of 100 robots at 10 Hz is 86
million poses. For each length, the simulated fleet's inputs (:func:`service.sim.wire.
fleet_records`, 360-beam scans at 10 Hz) are replayed once into a log that holds the inputs and
their poses, as a live log does (a replay's output is a valid replay input: its poses are the
recorded ones). That log is then audited in a fresh process, three times: ``rlutf replay LOG
--jobs 1`` (the audit alone: the recorded poses matched to the recomputed ones as they come,
:mod:`service.logs.posematch`), the same split between two processes by robot (``--jobs 2``,
:mod:`service.logs.split`; the peak is the largest process's), and
:func:`service.logs.replay.replay` keeping every pose in memory (``keep=True``: what ``rlutf
replay`` held until it matched the poses as they come, and what ``--plot`` still holds). Peak
resident memory is the process's ``ru_maxrss`` (the log is made in a process of its own, so
that the one that starts the audits stays small); time is wall-clock.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.report import section_main

SECTION = "replaymem"
T0 = 1_732_300_000_000_000_000
STEP_NS = 100_000_000
#: Poses of each robot's planned path; longer runs drive it back and forth.
PLAN_POSES = 301
KEEP = (
    "import sys; from pathlib import Path; from service.logs.replay import replay; "
    "r = replay([Path(sys.argv[1])], keep=True); "
    "print(sum(map(len, r.recorded.values())))"
)


def make_log(folder: Path, robots: int, steps: int) -> tuple[Path, int]:
    """A log of ``robots`` x ``steps`` scans with their poses; returns it and its poses."""
    from service.keys import Keys
    from service.logs.mcapfile import LogWriter
    from service.logs.replay import replay
    from service.sim.plan import FleetSpec, plan_fleet
    from service.sim.wire import JsonWire, fleet_records

    spec = FleetSpec(robots=robots, poses=PLAN_POSES, seed=3, map_id="m1")
    wire = JsonWire(plan_fleet(spec), Keys())
    inputs = folder / f"inputs-{steps}.mcap"
    with open(inputs, "wb") as stream:
        writer = LogWriter(stream)
        writer.write_all(fleet_records(wire, steps, T0, STEP_NS))
        writer.finish()
    log = folder / f"log-{steps}.mcap"
    result = replay([inputs], log, foxglove=False, keep=False)
    inputs.unlink()
    return log, result.match.recomputed_total


def peak(command: list[str]) -> tuple[float, float, int]:
    """Peak RSS (MB) and wall seconds of ``command`` run to its end, and its exit code."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_maxrss / 1024, time.perf_counter() - t0, proc.returncode


def make_log_apart(folder: Path, robots: int, steps: int) -> tuple[Path, int]:
    """:func:`make_log` in a process of its own: this one stays small, since a child's peak
    memory counts what it shared with its parent before it ran its command."""
    code = (
        "import sys; from pathlib import Path; from bench.replaymem import make_log; "
        "log, n = make_log(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])); print(n)"
    )
    args = [sys.executable, "-c", code, str(folder), str(robots), str(steps)]
    done = subprocess.run(args, check=True, capture_output=True, text=True)
    return folder / f"log-{steps}.mcap", int(done.stdout.split()[-1])


def measure(robots: int, steps: int, folder: Path) -> dict[str, float]:
    log, poses = make_log_apart(folder, robots, steps)
    rlutf = str(Path(sys.executable).with_name("rlutf"))
    audit_mb, audit_s, code = peak([rlutf, "replay", str(log), "--quiet", "--jobs", "1"])
    if code != 0:
        raise RuntimeError(f"rlutf replay {log}: exit {code}, the audit did not pass")
    split_mb, split_s, code = peak([rlutf, "replay", str(log), "--quiet", "--jobs", "2"])
    if code != 0:
        raise RuntimeError(f"rlutf replay {log} --jobs 2: exit {code}, the audit did not pass")
    keep_mb, keep_s, code = peak([sys.executable, "-c", KEEP, str(log)])
    if code != 0:
        raise RuntimeError(f"replay(keep=True) of {log}: exit {code}")
    size = log.stat().st_size / 1e6
    log.unlink()
    return {
        "steps": steps,
        "poses": poses,
        "log_mb": size,
        "audit_mb": audit_mb,
        "audit_s": audit_s,
        "split_mb": split_mb,
        "split_s": split_s,
        "keep_mb": keep_mb,
        "keep_s": keep_s,
    }


def render(args: argparse.Namespace) -> str:
    steps = [int(s) for s in args.steps.split(",")]
    with tempfile.TemporaryDirectory(prefix="rlutf-replaymem-") as tmp:
        rows = [measure(args.robots, s, Path(tmp)) for s in steps]
    shown = f"python -m bench.replaymem --robots {args.robots} --steps {args.steps}"
    lines = [
        f"Command: `{shown} --write`",
        "",
        f"Machine: {platform.machine()}, CPython {platform.python_version()}; {args.robots} "
        "simulated robots, 360-beam scans at 10 Hz, each log audited in a fresh process.",
        "",
        "| steps | poses | log MB | `rlutf replay LOG --jobs 1`: peak MB | s | `--jobs 2`: peak "
        "MB of a process | s | every pose kept (`replay(keep=True)`): peak MB | s |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {r['steps']:.0f} | {r['poses']:.0f} | {r['log_mb']:.1f} | {r['audit_mb']:.0f} | "
        f"{r['audit_s']:.1f} | {r['split_mb']:.0f} | {r['split_s']:.1f} | {r['keep_mb']:.0f} | "
        f"{r['keep_s']:.1f} |"
        for r in rows
    ]
    poses = np.array([r["poses"] for r in rows])
    for key, name in (("audit_mb", "`rlutf replay LOG --jobs 1`"), ("keep_mb", "every pose kept")):
        slope = float(np.polyfit(poses, np.array([r[key] for r in rows]), 1)[0]) * 1e6
        lines.append("")
        lines.append(
            f"{name}: {slope:.0f} MB per million poses (least-squares line through the rows)."
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.replaymem", description=__doc__)
    parser.add_argument("--robots", type=int, default=20, help="simulated robots")
    parser.add_argument(
        "--steps", default="300,600,1200,2400", help="scans per robot of each log, comma-separated"
    )
    return section_main(parser, render, SECTION, argv)


if __name__ == "__main__":
    sys.exit(main())
