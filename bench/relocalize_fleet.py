"""Does one robot's relocalization stall the others? (issue 13: their p99 stays under 50 ms)

Run: ``python -m bench.relocalize_fleet [--robots 20] [--duration 15] [--every 2] [--threads 4,1]
[--write]``.

A ``rlutf serve`` subprocess (router on a loopback port, embedded store, worker processes, no
recording) holds a large building (100 m x 60 m, where a global search takes a few tenths of a
second) and a fleet driven at 10 Hz with 360-beam scans precomputed before the clock starts:
``--robots`` steady robots and one more, the *kidnapped* one. The fleet runs two phases of
``--duration`` seconds on the same warm service: first with no relocalization, then with an
operator's Relocalize for the kidnapped robot every ``--every`` seconds (each one a search of
the whole map at its next scan). Reported per phase: the steady robots' scan-to-pose latency
(put to pose received, over Zenoh on loopback), their scans sent, poses received and scans the
service dropped; and the kidnapped robot's relocalizations: how many, how long each took (its
scan put to its pose) and how many ended ``corrected`` within 5 cm of the truth. The whole is run
once per ``--threads`` value (the service's ``worker_threads``: 1 is one update at a time per
worker, as before issue 13), each against a fresh service.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.fleetrun import health, start_service, stop_service
from bench.report import section_main

SECTION = "relocalize-fleet"
RATE_HZ = 10.0
KIDNAPPED = "kidnapped"


def _plan(robots: int, steps: int, seed: int, every: float, first: int) -> Any:
    """The fleet: ``robots`` steady robots and the kidnapped one (last), a Relocalize for it
    every ``every`` seconds from step ``first``."""
    from service.sim.plan import Building, FleetSpec, Schedule, plan_fleet

    spec = FleetSpec(
        robots=robots + 1,
        poses=steps,
        rate_hz=RATE_HZ,
        seed=seed,
        building=Building(width=100.0, height=60.0, rooms_x=10, rooms_y=6),
        map_id="big",
        robot_ids=(*(f"r{i:03d}" for i in range(robots)), KIDNAPPED),
        relocalize=Schedule(every=max(1, round(every * RATE_HZ)), first=first, robots=(robots,)),
    )
    return plan_fleet(spec)


def _drive(endpoint: str, robots: int, duration: float, every: float, seed: int) -> dict[str, Any]:
    import zenoh

    from service.live.sessions import client_config
    from service.sim.fleet import SimFleet, drive
    from service.sim.wire import JsonWire

    steps = int(2 * duration * RATE_HZ) + 20
    warm = 10  # steps before the first phase: localizers made, maps' fields built
    first_with = warm + steps // 2 - 10
    plan = _plan(robots, steps, seed, every, first_with)
    ids = [r.robot_id for r in plan.robots]
    put_at: dict[tuple[str, int], float] = {}
    got: dict[tuple[str, int], tuple[float, dict[str, Any]]] = {}
    events: list[tuple[float, dict[str, Any]]] = []
    lock = threading.Lock()

    def on_pose(sample: zenoh.Sample) -> None:
        now = time.monotonic()
        p = json.loads(sample.payload.to_bytes())
        with lock:
            got.setdefault((p["robot_id"], p["stamp_ns"]), (now, p))

    def on_event(sample: zenoh.Sample) -> None:
        with lock:
            events.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

    fleet = SimFleet(plan, JsonWire(plan), lambda: zenoh.open(client_config(endpoint)), 1)
    session = fleet.operator
    subs = [
        session.declare_subscriber("rlutf/robots/*/pose", on_pose),
        session.declare_subscriber(f"rlutf/robots/{KIDNAPPED}/events", on_event),
    ]
    fleet.put_map()
    time.sleep(1.0)
    t0 = time.time_ns()
    period = plan.spec.period_ns
    fleet.start(t0)
    phase_of: dict[int, str] = {}
    requests: list[tuple[float, int]] = []

    def on_step(k: int) -> None:
        phase_of[k] = "warm-up" if k < warm else "without" if k < first_with else "with"
        if fleet.extras(k, t0 + k * period):
            requests.append((time.monotonic(), k))

    def send(i: int, k: int) -> None:
        stamp = t0 + k * period
        fleet.odometry(i, k, stamp)
        put_at[(ids[i], stamp)] = time.monotonic()
        fleet.scan(i, k, stamp)

    drive(len(ids), 1.0 / RATE_HZ, send, steps - 1, on_step=on_step)
    time.sleep(3.0)
    for s in subs:
        s.undeclare()
    fleet.close()
    return {
        "t0": t0,
        "period_ns": period,
        "put_at": put_at,
        "got": got,
        "phase_of": phase_of,
        "requests": requests,
        "events": events,
        "truth": {r.robot_id: r.truth for r in plan.robots},
    }


def run(robots: int, duration: float, every: float, workers: int, threads: int) -> dict[str, Any]:
    """Both phases against a fresh service subprocess."""
    from service.live.sessions import free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-relocfleet-"))
    env = {"RLUTF_WORKER_THREADS": str(threads)}
    proc = start_service(endpoint, tmp, False, workers, env=env, instance="relocbench")
    try:
        time.sleep(3.0)
        data = _drive(endpoint, robots, duration, every, seed=5)
        data["health"] = health(endpoint)
    finally:
        stop_service(proc)
        shutil.rmtree(tmp, ignore_errors=True)
    return data


def summarize(data: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per phase: the steady robots' latency and counts; the relocalizations."""
    t0, period = data["t0"], data["period_ns"]
    out: dict[str, dict[str, Any]] = {}
    for phase in ("without", "with"):
        lat, sent, poses = [], 0, 0
        for (rid, stamp), put in data["put_at"].items():
            k = (stamp - t0) // period
            if rid == KIDNAPPED or data["phase_of"].get(k) != phase:
                continue
            sent += 1
            if (rid, stamp) in data["got"]:
                poses += 1
                lat.append(1e3 * (data["got"][(rid, stamp)][0] - put))
        a = np.asarray(lat) if lat else np.array([math.nan])
        out[phase] = {
            "sent": sent,
            "poses": poses,
            "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)),
            "max": float(a.max()),
        }
    # Each request's search runs at the kidnapped robot's next scan: its latency is the search.
    searches, found = [], 0
    truth = data["truth"][KIDNAPPED]
    for _, k in data["requests"]:
        stamp = t0 + k * period
        key = (KIDNAPPED, stamp)
        if key in data["got"]:
            at, pose = data["got"][key]
            searches.append(1e3 * (at - data["put_at"][key]))
            err = math.hypot(pose["x"] - truth[k, 0], pose["y"] - truth[k, 1])
            found += pose["status"] == "corrected" and err < 0.05
    s = np.asarray(searches) if searches else np.array([math.nan])
    codes = [e["code"] for _, e in data["events"]]
    out["relocalizations"] = {
        "requests": len(data["requests"]),
        "answered": len(searches),
        "found": found,
        "search_p50": float(np.percentile(s, 50)),
        "search_max": float(s.max()),
        "relocalized_events": codes.count("relocalized"),
        "dropped": int(data["health"].get("dropped", -1)),
    }
    return out


def render(robots: int, duration: float, every: float, workers: int, threads: list[int]) -> str:
    """The BENCHMARKS.md section."""
    rows, notes = [], []
    for t in threads:
        s = summarize(run(robots, duration, every, workers, t))
        r = s["relocalizations"]
        rows += [
            f"| {t} | {name} | {s[phase]['sent']} | {s[phase]['poses']} | {s[phase]['p50']:.1f} "
            f"| {s[phase]['p99']:.1f} | {s[phase]['max']:.1f} |"
            for phase, name in (("without", "none"), ("with", "one robot relocalizing"))
        ]
        notes.append(
            f"- `worker_threads={t}`: {r['requests']} relocalizations requested, "
            f"{r['answered']} answered, {r['found']} `corrected` within 5 cm of the truth at "
            f"their first scan, {r['relocalized_events']} Events `relocalized`; a search took "
            f"{r['search_p50']:.0f} ms (median, scan put to pose), {r['search_max']:.0f} ms at "
            f"most; scans dropped over the run, warm-up included: {r['dropped']}."
        )
    cmd = (
        f"python -m bench.relocalize_fleet --robots {robots} --duration {duration:g} "
        f"--every {every:g} --workers {workers} --threads {','.join(map(str, threads))} --write"
    )
    return "\n".join(
        [
            "## Relocalization in a fleet: the other robots' latency",
            "",
            "```bash",
            cmd,
            "```",
            "",
            f"{robots} steady robots and one kidnapped robot at 10 Hz, 360 beams, on a 100 m x "
            f"60 m building; `rlutf serve` with `--workers {workers}` on {os.cpu_count()} cores "
            f"({platform.processor() or platform.machine()}), shared with the load generator "
            f"(and whatever else ran on the machine). Two phases of {duration:g} s on the same "
            f"service: none, then a Relocalize of the kidnapped robot every {every:g} s (a "
            "search of the whole map at its next scan). Latency is the steady robots' scan put "
            "to pose received, over Zenoh on loopback.",
            "",
            "| worker_threads | relocalization | steady scans sent | poses received | p50 ms "
            "| p99 ms | max ms |",
            "| ---: | --- | ---: | ---: | ---: | ---: | ---: |",
            *rows,
            "",
            *notes,
            "",
            "With one thread per worker, a search holds every robot of its worker behind it "
            "(their scans are superseded and dropped meanwhile, or wait). With several, a "
            "worker runs the batches of robots that may take long (relocalizing or lost) on "
            "threads of their own beside the one that runs all the others; one robot's updates "
            "still run strictly in order and the compiled search releases the GIL, so a search "
            "holds up only its own robot. Scans dropped are superseded while their robot's "
            "update ran (most are the kidnapped robot's, during its searches).",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.relocalize_fleet",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=20, help="steady robots (plus one kidnapped)")
    p.add_argument("--duration", type=float, default=15.0, help="seconds per phase")
    p.add_argument("--every", type=float, default=2.0, help="seconds between Relocalize messages")
    p.add_argument(
        "--threads", default="4,1", help="the service's worker_threads values to run, commas"
    )
    p.add_argument("--workers", type=int, default=-1, help="service worker processes")

    def go(args: argparse.Namespace) -> str:
        threads = [int(t) for t in args.threads.split(",")]
        return render(args.robots, args.duration, args.every, args.workers, threads)

    return section_main(p, go, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
