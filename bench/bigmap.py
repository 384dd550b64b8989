"""What a map of real size costs, and whether a map of large extent can stall the fleet.

Run: ``python -m bench.bigmap [--mb 10] [--write]`` (issue 20 item 2, issue 19 item 2).

The map of real size is a generated warehouse: a hall with thousands of racks, each traced as a
scanner's map would be (a vertex every 5 cm, coordinates to the millimetre with 2 mm of noise),
sized to about ``--mb`` MB of JSON. First, in this process, one step at a time (time and the
peak of Python's allocations, ``tracemalloc``): parsing the JSON alone (``json.loads``), the
service's decode (pydantic, the schema), the main process's validation (:func:`load_map`:
decode, extent and vertex limits, geometry), a worker's build (decode, geometry, wall index,
distance field) and recording it (an MCAP recorder, to the file closed). Then live: an ``rlutf
serve`` subprocess (router on a loopback port, embedded store, 2 worker processes, recording on)
with 3 robots driven at 10 Hz on a small building; in turn: the warehouse put with ``rlutf map
put`` (put to the store's confirmation), loaded (put to ``map_updated``), and a robot on it
(InitialPose to its first pose); a 144-byte 2 km square (put to ``invalid_map``); a 40,000-vertex
room and a robot on it. For each, the steady robots' longest time without a pose and their
scan-to-pose latency from the put to the first pose on the new map (at least 5 s), and the peak
resident memory of the service (all its processes) over the run.
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
    from service.maps.book import load_map

    s = Settings()
    rows = []
    rows.append(("parse the JSON alone (json.loads)", *_measure(lambda: json.loads(payload))[:2]))
    rows.append(
        ("decode (pydantic: schema)", *_measure(lambda: decode(Map, payload, max_bytes=10**9))[:2])
    )
    rows.append(
        (
            "validate in the main process (decode, limits, geometry)",
            *_measure(
                lambda: load_map(
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


def _connect(config: Any, proc: subprocess.Popen[bytes]) -> Any:
    """A session to the service once it listens (it compiles or loads its kernels first)."""
    import zenoh

    for _ in range(600):
        if proc.poll() is not None:
            raise RuntimeError(f"rlutf serve exited with {proc.returncode}")
        try:
            return zenoh.open(config)
        except zenoh.ZError:
            time.sleep(0.2)
    raise RuntimeError("rlutf serve did not listen within 120 s")


def live(payload: bytes, racks_y: int, workers: int) -> dict[str, Any]:
    """The live part against a fresh ``rlutf serve`` subprocess."""

    from rlutf.map import Map as World
    from schemas import Map, decode, encode
    from service.live.sessions import client_config, free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="rlutf-bigmap-"))
    exe = shutil.which("rlutf", path=str(Path(sys.executable).parent)) or "rlutf"
    cmd = [exe, "serve", "--listen", endpoint, "--store", str(tmp / "store")]
    cmd += ["--record", str(tmp / "logs"), "--instance", "bigmap", "--workers", str(workers)]
    proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    out: dict[str, Any] = {}
    try:
        world = World.from_geojson(decode(Map, payload, max_bytes=10**9).geometry.model_dump())
        room = wavy_room(40_000)
        session = _connect(client_config(endpoint), proc)
        with PeakRss(proc.pid) as rss, session:
            time.sleep(3.0)
            rover = _robot_on(
                session, "rover", "wavy", World.from_geojson(room), np.array([0.0, 0.0, 0.0])
            )
            fleet = SteadyFleet(session, robots=3, seconds=60.0)
            fleet.start()
            events, sub = _events(session)
            fleet.wait_steady()
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
            subprocess.run(put, check=True, stdout=subprocess.DEVNULL)
            out["put_s"] = time.monotonic() - t0
            loaded = _wait(lambda: _seen(events, "map_updated", "warehouse"), 60.0)
            out["load_s"] = None if loaded is None else loaded + out["put_s"]
            out["first_pose_s"] = picker()
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
    run = live(payload, racks_y, args.workers)
    buf = io.StringIO()
    w = buf.write
    w(f"## {SECTION}\n\n")
    w(
        f"`python -m bench.bigmap --mb {args.mb:g} --workers {args.workers} --write` "
        f"({os.cpu_count()} cores, shared). A warehouse of {holes:,} racks traced at 5 cm: "
        f"{len(payload) / 1e6:.1f} MB of JSON, {vertices:,} vertices.\n\n"
    )
    w("| step, in one process | time | peak allocations |\n| --- | ---: | ---: |\n")
    for name, seconds, peak in rows:
        w(f"| {name} | {seconds:.2f} s | {peak:.0f} MB |\n")
    t = {name.split(" (")[0]: seconds for name, seconds, _ in rows}
    parse, decode = t["parse the JSON alone"], t["decode"]
    check = t["validate in the main process"]
    w(
        f"\nJSON: the main process's validation ({check:.2f} s) is mostly the schema's decode "
        f"({decode:.2f} s; `json.loads` alone takes {parse:.2f} s); both are C code that holds "
        "the interpreter's lock throughout, so the service validates maps in a process of its "
        "own (`MapChecker`, isolated when there are worker processes) and its Zenoh callbacks "
        "run on. The worker's build is mostly the distance field of the wide search (compiled, "
        "in proportion to the walls), on the slow lane of the worker whose robot needs it.\n"
    )
    w(
        "\nLive (`rlutf serve`, 2 workers, recording; 3 robots at 10 Hz on another map; the "
        "steady robots from each put to the first pose on that map, at least 5 s):\n\n"
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
    row(
        "warehouse: `rlutf map put` to stored; to `map_updated`; first pose on it",
        f"{fmt(run['put_s'])}; {fmt(run['load_s'])}; {fmt(run['first_pose_s'])}",
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
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.bigmap",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--mb", type=float, default=10.0, help="size of the warehouse map, MB")
    p.add_argument("--workers", type=int, default=2, help="service worker processes")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
