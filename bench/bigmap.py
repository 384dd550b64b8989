"""What a map of real size costs, and whether a map of large extent can stall the fleet.

Run: ``python -m bench.bigmap [--mb 10] [--processes N | --workers N] [--write]`` (issue 20
item 2, issue 19 item 2).

The map of real size is a generated warehouse: a hall with thousands of racks, each traced as a
scanner's map would be (a vertex every 5 cm, coordinates to the millimetre with 2 mm of noise),
sized to about ``--mb`` MB of JSON. First, in this process, one step at a time (time and the
peak of Python's allocations, ``tracemalloc``): parsing the JSON alone (``json.loads``), the
service's decode (pydantic, the schema), the validation (:func:`check_map`: decode, extent and
vertex limits, geometry, content digest; the map checker's process does it), a worker's build
(decode, geometry, wall index, distance field) and recording it (an MCAP recorder, to the file
closed). Then live: an ``rlutf serve`` subprocess (router on a loopback port, embedded store,
recording on) in the service's default layout (``--processes N``, N as
:func:`bench.fleetrun.serve_layout` resolves it: one process per usable core) or, with
``--workers N``, the layout of worker processes, with 3 robots driven at 10 Hz on a small
building; in turn: the warehouse put with ``rlutf map put`` (put to the store's confirmation),
loaded (put to ``map_updated``), and a robot on it (InitialPose to its first pose); a 144-byte 2
km square (put to ``invalid_map``); a 40,000-vertex room and a robot on it. For each, the steady
robots' longest time without a pose and their scan-to-pose latency from the put to the first
pose on the new map (at least 5 s), and the peak resident memory of the service (all its
processes) in each phase and of each of its processes over the run.
"""

from __future__ import annotations

import argparse
import gc
import io
import itertools
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.fleetrun import layout_text, serve_layout
from bench.mapload import (
    JSON_ENCODING,
    PeakRss,
    SteadyFleet,
    scan_payload,
    square_map,
    wavy_room,
)
from bench.report import section_main

SECTION = "Maps of real size and of large extent"
#: The section of a run in the layout of workers (``--workers N``).
WORKERS_SECTION = f"{SECTION}: the layout of workers"
RACK = (1.0, 2.0)  # x, y size of a rack, metres
PITCH = (3.0, 2.6)  # rack spacing: 2 m aisles between rows, 0.6 m between racks in a row


def warehouse(racks_x: int, racks_y: int, step: float = 0.05, seed: int = 7) -> dict[str, Any]:
    """A hall of ``racks_x * racks_y`` traced racks around a 4 m cross aisle (GeoJSON).

    The cross aisle runs along x at ``y = aisle_y(racks_y)``; racks sit in rows of ``racks_y // 2``
    on each side of it.
    """
    rng = np.random.default_rng(seed)
    margin = 3.0
    half = racks_y // 2
    width = 2 * margin + racks_x * PITCH[0]
    height = 2 * margin + racks_y * PITCH[1] + 4.0
    holes = []
    for i in range(racks_x):
        for j in range(racks_y):
            x = margin + i * PITCH[0] + (PITCH[0] - RACK[0]) / 2
            y = margin + j * PITCH[1] + (4.0 if j >= half else 0.0)
            holes.append(_traced_rect(x, y, RACK[0], RACK[1], step, rng)[::-1])  # clockwise
    shell = [[0.0, 0.0], [width, 0.0], [width, height], [0.0, height], [0.0, 0.0]]
    return {"type": "Polygon", "coordinates": [shell, *holes]}


def aisle_y(racks_y: int) -> float:
    """The middle of the warehouse's cross aisle, metres."""
    return 3.0 + (racks_y // 2) * PITCH[1] + 2.0


def _traced_rect(
    x: float, y: float, w: float, h: float, step: float, rng: np.random.Generator
) -> list[list[float]]:
    corners = [(x, y), (x + w, y), (x + w, y + h), (x, y + h), (x, y)]
    pts: list[np.ndarray] = []
    for (ax, ay), (bx, by) in itertools.pairwise(corners):
        n = max(round(math.hypot(bx - ax, by - ay) / step), 1)
        t = np.arange(n) / n
        pts.append(np.column_stack([ax + t * (bx - ax), ay + t * (by - ay)]))
    ring = np.vstack(pts)
    ring[1:] += rng.normal(0.0, 0.002, ring[1:].shape)
    ring = np.round(ring, 3)
    return [*ring.tolist(), ring[0].tolist()]


def warehouse_payload(mb: float, map_id: str = "warehouse") -> tuple[bytes, int]:
    """A warehouse Map of about ``mb`` MB; returns the payload and ``racks_y``."""
    from schemas import Map, encode

    racks_y = 40
    per_rack = 2.0 * (RACK[0] + RACK[1]) / 0.05 * 16  # bytes: a vertex is about 16
    racks_x = max(round(mb * 1e6 / per_rack / racks_y), 1)
    geometry = warehouse(racks_x, racks_y)
    return encode(Map(map_id=map_id, version=1, geometry=geometry)), racks_y


def _measure(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Seconds (a plain run) and peak MB of Python's allocations (a second run, traced:
    tracing slows allocations several times over)."""
    t0 = time.perf_counter()
    fn()
    seconds = time.perf_counter() - t0
    tracemalloc.start()
    out = fn()
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return seconds, peak, out


def offline(payload: bytes) -> list[tuple[str, float, float]]:
    """Each step's ``(name, seconds, peak MB)`` in this process."""
    from rlutf.field import distance_field
    from schemas import Map, decode
    from service.config import Settings
    from service.live.worker import world_of_payload
    from service.logs.mcaplog import McapRecorder
    from service.maps.book import check_map

    s = Settings()
    rows = []
    rows.append(("parse the JSON alone (json.loads)", *_measure(lambda: json.loads(payload))[:2]))
    rows.append(
        ("decode (pydantic: schema)", *_measure(lambda: decode(Map, payload, max_bytes=10**9))[:2])
    )
    rows.append(
        (
            "validate (decode, limits, geometry, digest)",
            *_measure(
                lambda: check_map(
                    payload, expected_id=None, max_bytes=s.max_map_bytes, limits=s.map_limits()
                )
            )[:2],
        )
    )

    def build() -> Any:
        world = world_of_payload(payload)
        world.index  # noqa: B018
        return distance_field(world)

    rows.append(("build in a worker (decode, geometry, index, field)", *_measure(build)[:2]))
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-bigmap-rec-"))

    def record() -> None:
        rec = McapRecorder(tmp, instance="bench")
        rec.record("rlutf/maps/warehouse", "rlutf.Map", payload, time.time_ns(), time.time_ns())
        rec.close()

    rows.append(("record (MCAP recorder, until the file is closed)", *_measure(record)[:2]))
    shutil.rmtree(tmp, ignore_errors=True)
    return rows


def _events(session: Any) -> tuple[list[tuple[float, dict[str, Any]]], Any]:
    seen: list[tuple[float, dict[str, Any]]] = []
    sub = session.declare_subscriber(
        "rlutf/events",
        lambda s: seen.append((time.monotonic(), json.loads(s.payload.to_bytes()))),
    )
    return seen, sub


def _seen(events: list[tuple[float, dict[str, Any]]], code: str, map_id: str) -> bool:
    return any(e["code"] == code and e["key"].endswith(f"/{map_id}") for _, e in events)


def _count(events: list[tuple[float, dict[str, Any]]], code: str, map_id: str) -> int:
    """Events of ``code`` about ``map_id`` (one from each process that loaded it, say)."""
    return sum(e["code"] == code and e["key"].endswith(f"/{map_id}") for _, e in events)


def _since(t0: float, pred: Callable[[], Any], timeout: float) -> float | None:
    """Seconds from ``t0`` (monotonic) until ``pred`` holds, waiting until ``timeout`` seconds
    after ``t0`` at most (``None``: it did not hold by then)."""
    waited = _wait(pred, max(t0 + timeout - time.monotonic(), 0.0))
    return None if waited is None else time.monotonic() - t0


def _wait(pred: Callable[[], Any], timeout: float) -> float | None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return time.monotonic() - t0
        time.sleep(0.01)
    return None


def _robot_on(session: Any, robot: str, map_id: str, world: Any, pose: np.ndarray) -> Any:
    """A robot standing at ``pose`` on a map: call the result to send its InitialPose and a
    scan every 0.1 s until its first pose comes; it returns the seconds that took (None:
    none in 30 s). The scan is simulated here, before any clock runs."""
    from rlutf.sim import LidarModel, simulate_scan
    from schemas import InitialPose, Odometry, encode

    s = simulate_scan(world, pose, LidarModel(beams=360), np.random.default_rng(1))
    x, y, th = (float(v) for v in pose)

    def go() -> float | None:
        got: list[float] = []
        sub = session.declare_subscriber(f"rlutf/robots/{robot}/pose", lambda _: got.append(1))
        t0 = time.monotonic()
        stamp = time.time_ns()
        odom = encode(Odometry(stamp_ns=stamp, x=x, y=y, theta=th))
        session.put(f"rlutf/robots/{robot}/odom", odom)
        init = InitialPose(stamp_ns=stamp, map_id=map_id, x=x, y=y, theta=th)
        session.put(f"rlutf/robots/{robot}/initialpose", encode(init))
        try:
            for k in range(1, 300):
                st = stamp + k * 100_000_000
                odom = encode(Odometry(stamp_ns=st, x=x, y=y, theta=th))
                session.put(f"rlutf/robots/{robot}/odom", odom)
                session.put(
                    f"rlutf/robots/{robot}/scan", scan_payload(s, st), encoding=JSON_ENCODING
                )
                if _wait(lambda: got, 0.1) is not None:
                    return time.monotonic() - t0
            return None
        finally:
            sub.undeclare()

    return go


def _connect(config: Any, endpoint: str, proc: subprocess.Popen[bytes]) -> Any:
    """A session to the service once it is ready (every process of it; it compiles or loads
    its kernels first)."""
    import zenoh

    from bench.fleetrun import wait_ready

    wait_ready(endpoint, proc, timeout=600.0, instance="bigmap")
    return zenoh.open(config)


def live(payload: bytes, racks_y: int, workers: int, processes: int) -> dict[str, Any]:
    """The live part against a fresh ``rlutf serve`` subprocess (``processes`` service
    processes, or with 0 the layout of ``workers`` worker processes)."""

    from rlutf.map import Map as World
    from schemas import Map, decode, encode
    from service.live.sessions import client_config, free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-bigmap-"))
    exe = shutil.which("rlutf", path=str(Path(sys.executable).parent)) or "rlutf"
    cmd = [exe, "serve", "--listen", endpoint, "--store", str(tmp / "store")]
    cmd += ["--record", str(tmp / "logs"), "--instance", "bigmap"]
    cmd += ["--processes", str(processes)] if processes else ["--workers", str(workers)]
    proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    out: dict[str, Any] = {}
    try:
        world = World.from_geojson(decode(Map, payload, max_bytes=10**9).geometry.model_dump())
        room = wavy_room(40_000)
        session = _connect(client_config(endpoint), endpoint, proc)
        with PeakRss(proc.pid) as rss, session:
            time.sleep(3.0)
            rover = _robot_on(
                session, "rover", "wavy", World.from_geojson(room), np.array([0.0, 0.0, 0.0])
            )
            fleet = SteadyFleet(session, robots=3, seconds=90.0)
            fleet.start()
            events, sub = _events(session)
            fleet.wait_steady()
            time.sleep(5.0)  # a window of steady driving (before, it began before the fleet)
            out["before"] = fleet.window(time.monotonic() - 5.0, time.monotonic())
            out["rss_before_mb"] = rss.restart()
            # The warehouse, with `rlutf map put` (a process of its own, as an operator's).
            path = tmp / "warehouse.json"
            path.write_bytes(payload)
            picker = _robot_on(
                session, "picker", "warehouse", world, np.array([10.0, aisle_y(racks_y), 0.0])
            )
            t0 = time.monotonic()
            put = [exe, "map", "put", str(path), "--connect", endpoint, "--timeout", "60"]
            tool = subprocess.Popen(put, stdout=subprocess.DEVNULL)  # it waits for every process
            loads = lambda: _count(events, "map_updated", "warehouse")  # noqa: E731
            out["load_s"] = _since(t0, lambda: loads() >= 1, 60.0)  # the first process
            out["first_pose_s"] = picker()
            out["load_all_s"] = _since(t0, lambda: loads() >= max(processes, 1), 60.0)
            out["loaded_by"] = loads()
            tool.wait(90.0)
            out["put_s"] = time.monotonic() - t0  # to `rlutf map put`'s end, at most
            time.sleep(max(t0 + 5.0 - time.monotonic(), 0.0))
            out["warehouse"] = fleet.window(t0, time.monotonic())
            out["rss_warehouse_mb"] = rss.restart()
            # A 2 km square.
            t0 = time.monotonic()
            session.put("rlutf/maps/square2km", square_map("square2km", 2000.0))
            out["square_event_s"] = _wait(lambda: _seen(events, "invalid_map", "square2km"), 10.0)
            time.sleep(max(t0 + 5.0 - time.monotonic(), 0.0))
            out["square"] = fleet.window(t0, t0 + 5.0)
            out["rss_square_mb"] = rss.restart()
            # A 40,000-vertex room, and a robot on it.
            t0 = time.monotonic()
            session.put("rlutf/maps/wavy", encode(Map(map_id="wavy", version=1, geometry=room)))
            _wait(lambda: _seen(events, "map_updated", "wavy"), 10.0)
            out["wavy_first_pose_s"] = rover()
            time.sleep(max(t0 + 5.0 - time.monotonic(), 0.0))
            out["wavy"] = fleet.window(t0, time.monotonic())
            out["rss_wavy_mb"] = rss.restart()
            sub.undeclare()
            fleet.stop()
        out["rss_peak_mb"] = rss.peak
        out["rss_by_role_mb"] = dict(rss.by_role)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        out["log_mb"] = sum(p.stat().st_size for p in (tmp / "logs").glob("*.mcap")) / 1e6
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def render(args: argparse.Namespace) -> str:
    """The BENCHMARKS.md section."""
    payload, racks_y = warehouse_payload(args.mb)
    geometry = json.loads(payload)["geometry"]
    holes = len(geometry["coordinates"]) - 1
    vertices = sum(len(r) for r in geometry["coordinates"])
    del geometry  # millions of objects: every collection of this process walked them
    rows = offline(payload)
    gc.collect()
    gc.freeze()  # the fleet's thread in this process must not pause for collections
    workers, processes = serve_layout(args.workers, args.processes)
    load = os.getloadavg()[0]
    started = time.strftime("%H:%M UTC", time.gmtime())
    run = live(payload, racks_y, workers, processes)
    buf = io.StringIO()
    w = buf.write
    flag = f"--processes {processes}" if processes else f"--workers {workers}"
    if processes:
        w(f"## {SECTION}\n\n")
    else:
        w(f"### {SECTION}, in the layout of workers\n\n")
    w(
        f"`python -m bench.bigmap --mb {args.mb:g} {flag} --write` "
        f"({os.cpu_count()} cores, shared; load average {load:.2f} at the start, {started}). "
        f"A warehouse of {holes:,} racks traced at 5 cm: "
        f"{len(payload) / 1e6:.1f} MB of JSON, {vertices:,} vertices.\n\n"
    )
    w("| step, in one process | time | peak allocations |\n| --- | ---: | ---: |\n")
    for name, seconds, peak in rows:
        w(f"| {name} | {seconds:.2f} s | {peak:.0f} MB |\n")
    t = {name.split(" (")[0]: seconds for name, seconds, _ in rows}
    parse, decode = t["parse the JSON alone"], t["decode"]
    check = t["validate"]
    w(
        f"\nJSON: the validation ({check:.2f} s) is mostly the schema's decode ({decode:.2f} s; "
        f"`json.loads` alone takes {parse:.2f} s), the geometry's validity and the digest's "
        "encoding, C code that holds the interpreter's lock for up to a third of a second at a "
        "time, so the service validates maps in a process of its own (`MapChecker`), which, in "
        "each process of the default layout, sends the map back validated (its walls and "
        "geometry); the service's threads run on meanwhile. The build (wall index, distance "
        "field of the wide search, simplified walls) is compiled code that lets go of the lock, "
        "and short Python steps, on the slow lane of the process (or worker) whose robot "
        "needs the map.\n"
    )
    what = f"{workers} workers" if not processes else layout_text(processes)
    w(
        f"\nLive (`rlutf serve {flag}`, {what}, recording; 3 robots at 10 Hz on another map; "
        "the steady robots from each put to the first pose on that map, at least 5 s):\n\n"
    )
    w(
        "| | time | steady robots: longest without a pose | latency p50 / p99 / max | "
        "answered | service memory, peak |\n| --- | ---: | ---: | ---: | ---: | ---: |\n"
    )

    def fmt(x: Any) -> str:
        return "none" if x is None else f"{x:.2f} s"

    def row(name: str, t: str, win: dict[str, float], rss: float) -> None:
        w(
            f"| {name} | {t} | {win['max_gap_s']:.2f} s | {win['p50_ms']:.0f} / "
            f"{win['p99_ms']:.0f} / {win['max_ms']:.0f} ms | {100 * win['answered']:.0f} % | "
            f"{rss:.0f} MB |\n"
        )

    row("before any put", "", run["before"], run["rss_before_mb"])
    every = fmt(run["load_all_s"])
    if run["load_all_s"] is None:
        every = f"{run['loaded_by']} of {max(processes, 1)} processes in 60 s"
    row(
        "warehouse: to `map_updated` (the first process; every process); first pose on it; "
        "`rlutf map put` to its end",
        f"{fmt(run['load_s'])}; {every}; {fmt(run['first_pose_s'])}; {fmt(run['put_s'])}",
        run["warehouse"],
        run["rss_warehouse_mb"],
    )
    row(
        "2 km square (144 B): to `invalid_map`",
        fmt(run["square_event_s"]),
        run["square"],
        run["rss_square_mb"],
    )
    row(
        "40,000-vertex room: first pose on it",
        fmt(run["wavy_first_pose_s"]),
        run["wavy"],
        run["rss_wavy_mb"],
    )
    w(
        f"\nService memory: resident, all its processes (main, workers, map checker), peak "
        f"over each phase; over the run {run['rss_peak_mb']:.0f} MB. Log written: "
        f"{run['log_mb']:.1f} MB.\n"
    )
    w(
        "\nEach process's peak over the run (resident; `host` is the process started, `pK` "
        "its service processes, a child a process it spawned: worker, map checker):\n\n"
        "| process | peak |\n| --- | ---: |\n"
    )
    for role, mb in sorted(run["rss_by_role_mb"].items()):
        w(f"| {role} | {mb:.0f} MB |\n")
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.bigmap",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--mb", type=float, default=10.0, help="size of the warehouse map, MB")
    p.add_argument(
        "--processes",
        type=int,
        default=None,
        help="service processes (default: the service's own layout, one per usable core)",
    )
    p.add_argument(
        "--workers", type=int, default=None, help="worker processes: the layout of workers"
    )
    return section_main(
        p,
        render,
        lambda a: WORKERS_SECTION if serve_layout(a.workers, a.processes)[1] == 0 else SECTION,
        argv,
    )


if __name__ == "__main__":
    raise SystemExit(main())
