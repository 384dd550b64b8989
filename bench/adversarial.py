"""The adversarial campaign (issue 19): can any input stop the fleet?

Run: ``python -m bench.adversarial [--classes burst-good,map-2km,...] [--quick] [--write]``.

For each attack class (:mod:`bench.attacks`), a fresh ``rlutf serve`` subprocess (a router on a
loopback port, embedded store, two worker processes, recording on) serves three good robots
driving at 10 Hz (a separate process: simulated runs on the map ``bench``, 360-beam scans) while
the attacker, a client of the same router, runs the class. Measured per class:

- health: the service's Health queried every 0.5 s with a 2 s timeout, over the whole run:
  the slowest answer and how many queries went unanswered;
- the good robots' answered share (scans sent after their first 2 s that got their pose), and
  the longest time any of them went without a pose (from the attack's start);
- the largest error of a good robot's pose against the truth among poses not ``lost``;
- Events the attacker saw (``rlutf/events`` and ``rlutf/robots/*/events``), by code;
- the service's resident memory (main process and workers) before the attack, at its peak and
  at the end;
- the time from SIGTERM to the service's exit (killed after 15 s).

``map-flood`` puts a 5 MB map one version newer each time, as fast as the attacker can, and
must leave the service on the version the store holds (the last put, unless the store dropped
it too, with an Event that asks for it again). ``mixed`` (every cheap class at 80 messages/s)
is compared with ``none``, the same run without
attack. The last column names the issue's targets a class missed.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench.attacks import CLASSES, Context
from bench.fleetrun import query_health, start_service
from bench.goodrobots import GOOD, RATE_HZ, WARMUP_S, drive, score
from bench.procstat import rss_tree_mb
from bench.report import section_main

SECTION = "adversarial"
HEALTH_EVERY_S = 0.5
HEALTH_TIMEOUT_S = 2.0
TERM_TIMEOUT_S = 15.0
#: Classes after which no good robot may go longer than this without a pose, seconds.
#: What ``--quick`` runs unless ``--classes`` says otherwise: the reference and the mix of all
#: cheap classes (under a minute in all).
QUICK_CLASSES = ["none", "mixed"]
GAP_TARGETS = {
    "map-2km": 1.0,
    "map-40k": 1.0,
    "map-flood": 1.0,
    "scan-1e5": 1.0,
    "kill-worker": 2.0,
}


class Probe:
    """Health every 0.5 s, and the service's memory, on a thread of their own."""

    def __init__(self, endpoint: str, pid: int) -> None:
        self.endpoint = endpoint
        self.pid = pid
        self.latencies: list[float] = []
        self.missed = 0
        self.rss: list[tuple[float, float]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="probe", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        import zenoh

        from service.live.sessions import client_config

        with zenoh.open(client_config(self.endpoint)) as session:
            while not self.stop.is_set():
                t0 = time.monotonic()
                self.rss.append((t0, rss_tree_mb(self.pid)))
                answered = any(
                    r.ok is not None
                    for r in session.get("rlutf/service/*/health", timeout=HEALTH_TIMEOUT_S)
                )
                took = time.monotonic() - t0
                if answered and took <= HEALTH_TIMEOUT_S:
                    self.latencies.append(took)
                else:
                    self.missed += 1
                self.stop.wait(max(HEALTH_EVERY_S - took, 0.0))

    def close(self) -> None:
        self.stop.set()
        if self.thread.is_alive():
            self.thread.join(HEALTH_TIMEOUT_S + 2.0)


def _wait_for_health(endpoint: str, timeout: float) -> bool:
    import zenoh

    from service.live.sessions import client_config

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with zenoh.open(client_config(endpoint)) as session:
                while time.monotonic() < deadline:
                    if query_health(session, timeout=1.0):
                        return True
                    time.sleep(0.3)
        except zenoh.ZError:  # the router is not listening yet
            time.sleep(0.5)
    return False


def _terminate(proc: subprocess.Popen[bytes]) -> float | None:
    """SIGTERM, and the seconds to exit; ``None`` when it had to be killed."""
    t0 = time.monotonic()
    proc.terminate()
    try:
        proc.wait(TERM_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None
    return time.monotonic() - t0


def run_class(
    name: str, duration: float, scale: float, workers: int, keep: Path | None = None
) -> dict[str, Any]:
    """One attack class against a fresh service, three good robots beside it.

    ``keep``: a folder to copy the service's log into (``CLASS.log``).
    """
    import zenoh

    from service.live.sessions import client_config, free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-adversarial-"))
    log = open(tmp / "service.log", "wb")  # noqa: SIM115 -- closed below
    proc = start_service(endpoint, tmp, True, workers, stderr=log)
    ctx_mp = mp.get_context("spawn")
    out, ready, go = ctx_mp.Queue(), ctx_mp.Event(), ctx_mp.Event()
    robots = ctx_mp.Process(target=drive, args=(endpoint, duration, 7, out, ready, go))
    probe = Probe(endpoint, proc.pid)
    row: dict[str, Any] = {"class": name, "duration": duration, "notes": []}
    events: Counter[str] = Counter()
    try:
        if not _wait_for_health(endpoint, 90.0):
            raise RuntimeError("the service never answered health")
        robots.start()
        if not ready.wait(300):
            raise RuntimeError("the good robots never got ready")
        starts = out.get(timeout=10)
        probe.start()
        with zenoh.open(client_config(endpoint)) as session:

            def on_event(sample: Any) -> None:
                import json

                try:
                    events[json.loads(sample.payload.to_bytes()).get("code", "?")] += 1
                except ValueError:
                    events["?"] += 1

            subs = [
                session.declare_subscriber(k, on_event)
                for k in ("rlutf/events", "rlutf/robots/*/events")
            ]
            go.set()
            time.sleep(WARMUP_S + 1.0)
            attack_for = max(duration - WARMUP_S - 1.5, 1.0)
            ctx = Context(session, proc.pid, list(GOOD), starts, scale, attack_for)
            row["rss_before"] = rss_tree_mb(proc.pid)
            attack_start = time.monotonic()
            row["sent"] = CLASSES[name](ctx)
            row["attack_s"] = time.monotonic() - attack_start
            row["notes"] += ctx.notes
            row.update(ctx.extra)
            result = out.get(timeout=duration + 120)
            for sub in subs:
                sub.undeclare()
        row.update(score(result, attack_start))
    except Exception as err:  # a class that breaks the bench must not stop the campaign
        row["notes"].append(f"bench error: {type(err).__name__}: {err}")
    finally:
        probe.close()
        row["term_s"] = _terminate(proc) if proc.poll() is None else math.nan
        if robots.pid is not None:
            robots.join(10)
            if robots.is_alive():
                robots.kill()
        log.close()
        if keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            shutil.copy(tmp / "service.log", keep / f"{name}.log")
        shutil.rmtree(tmp, ignore_errors=True)
    row["events"] = dict(events)
    row["health_max"] = max(probe.latencies, default=math.nan)
    row["health_missed"] = probe.missed
    rss = [mb for _, mb in probe.rss]
    row["rss_peak"] = max(rss, default=math.nan)
    row["rss_end"] = rss[-1] if rss else math.nan
    return row


def misses(row: dict[str, Any], reference: dict[str, Any] | None) -> list[str]:
    """The issue's targets a class missed."""
    out = []
    if row.get("health_missed", 1) or not row.get("health_max", math.inf) <= HEALTH_TIMEOUT_S:
        out.append("health")
    # A fake instance token takes robots away while it lives, by design where nothing controls
    # who may declare one (README, "What no message can do"): its target is the pose error.
    if row["class"] != "forged-pose" and not row.get("answered", 0.0) >= 0.9:
        out.append("answered")
    gap = GAP_TARGETS.get(row["class"])
    if gap is not None and not row.get("gap", math.inf) <= gap:
        out.append("gap")
    if not row.get("error", math.inf) <= 0.5:
        out.append("error")
    if not row.get("rss_peak", math.inf) < 1024:
        out.append("rss")
    if row["class"] == "many-ids" and not (
        row.get("rss_end", math.inf) - row.get("rss_before", 0.0) <= 100
    ):
        out.append("growth")
    if row["class"] == "map-flood" and row.get("last_loaded") != row.get("stored"):
        out.append("map")  # the service must end on the map the store holds
    term = row.get("term_s")
    if term is None or not term <= 10.0:
        out.append("sigterm")
    if (
        row["class"] == "mixed"
        and reference is not None
        and not row.get("answered", 0.0) >= reference.get("answered", 1.0) - 0.05
    ):
        out.append("vs none")
    if any(n.startswith("bench error") for n in row["notes"]):
        out.append("bench")
    return out


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "killed"
    if isinstance(value, float) and math.isnan(value):
        return "-"
    return format(value, spec)


def table(rows: list[dict[str, Any]]) -> list[str]:
    """Markdown rows of the campaign, one per class."""
    reference = next((r for r in rows if r["class"] == "none"), None)
    lines = [
        "| class | messages | health slowest s (unanswered) | good robots answered % "
        "| longest gap without a pose s | max error m (not lost) | Events seen "
        "| RSS MB before / peak / end | SIGTERM to exit s | missed targets |",
        "| --- | ---: | --- | ---: | ---: | ---: | --- | --- | ---: | --- |",
    ]
    for r in rows:
        rss = " / ".join(
            _fmt(r.get(k, math.nan), ".0f") for k in ("rss_before", "rss_peak", "rss_end")
        )
        ev = ", ".join(f"{k} {v}" for k, v in sorted(r.get("events", {}).items())) or "-"
        missed = misses(r, reference)
        notes = "; ".join(r["notes"])
        lines.append(
            f"| {r['class']} | {r.get('sent', '-')} "
            f"| {_fmt(r.get('health_max', math.nan), '.2f')} ({r.get('health_missed', '-')}) "
            f"| {_fmt(100 * r.get('answered', math.nan), '.1f')} "
            f"| {_fmt(r.get('gap', math.nan), '.2f')} | {_fmt(r.get('error', math.nan), '.3f')} "
            f"| {ev} | {rss} "
            f"| {_fmt(r.get('term_s', math.nan), '.1f')} "
            f"| {', '.join(missed) or 'none'}{f' ({notes})' if notes else ''} |"
        )
    return lines


def render(args: argparse.Namespace) -> str:
    """Run the chosen classes and return the Markdown section."""
    default = QUICK_CLASSES if args.quick else list(CLASSES)
    names = [c for c in args.classes.split(",") if c] if args.classes else default
    unknown = [c for c in names if c not in CLASSES]
    if unknown:
        raise SystemExit(f"unknown class(es): {', '.join(unknown)} (known: {', '.join(CLASSES)})")
    quick = args.quick
    duration = args.duration or (8.0 if quick else 20.0)
    long = args.mixed_duration or (8.0 if quick else 60.0)
    scale = 0.05 if quick else 1.0
    # Compile (or load) the localizer's kernels once, as the service's workers will: a worker
    # compiling for a minute would be counted against the first classes.
    subprocess.run(
        [sys.executable, "-c", "from rlutf.warmup import warm_up; warm_up()"], check=True
    )
    rows = []
    for name in names:
        # ``none`` is the reference of ``mixed``: the same length
        length = long if name in ("mixed", "none") and "mixed" in names else duration
        row = run_class(name, length, scale, args.workers, args.logs)
        rows.append(row)
        print(table([row])[-1], flush=True)
    command = "python -m bench.adversarial" + (" --quick" if quick else "")
    if args.classes:
        command += f" --classes {args.classes}"
    if args.duration:
        command += f" --duration {args.duration:g}"
    if args.mixed_duration:
        command += f" --mixed-duration {args.mixed_duration:g}"
    if args.workers != 2:
        command += f" --workers {args.workers}"
    return "\n".join(
        [
            f"Command: `{command}`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}. Per class a fresh `rlutf serve` ({args.workers} "
            f"workers, recording on), three good robots at {RATE_HZ:g} Hz for {duration:g} s "
            + (f"({long:g} s for none and mixed)" if "mixed" in names else "")
            + f"; counts scaled by {scale:g}. Targets (issue 19): "
            "health answers within 2 s throughout; good robots >= 90 % answered (but for "
            "forged-pose, whose fake instance token takes robots away while it lives); no gap over "
            "1 s (2 s after kill-worker); no pose off by more than 0.5 m unless lost; RSS under "
            "1 GB; many-ids growth <= 100 MB; map-flood ends on the store's map; SIGTERM "
            "exit within 10 s; mixed within 5 points of none.",
            "",
            *table(rows),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.adversarial",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--classes", help=f"comma-separated, of: {', '.join(CLASSES)} (default: all)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="CI smoke run (under a minute): none and mixed unless --classes, 8 s each, "
        "counts / 20",
    )
    p.add_argument("--duration", type=float, help="seconds per class (default 20; quick 8)")
    p.add_argument(
        "--mixed-duration", type=float, help="seconds of mixed and none (default 60; quick 8)"
    )
    p.add_argument("--workers", type=int, default=2, help="service worker processes")
    p.add_argument("--logs", type=Path, help="keep each class's service log in this folder")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
