"""A steady fleet beside a map load: do other robots keep their poses while a map loads?

Shared by :mod:`bench.bigmap` and the service tests of maps of real size and large extent:
:class:`SteadyFleet` drives robots at 10 Hz on a small building from a thread, with scans
computed before the clock starts, and times every pose; :class:`PeakRss` samples the resident
memory of a process and its children; :func:`big_maps` makes the maps the issues name.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.procstat import descendants

RATE_HZ = 10.0
JSON_ENCODING = "application/json"


def scan_payload(s: Any, stamp_ns: int) -> bytes:
    """The LaserScan payload of a simulated :class:`rlutf.scan.Scan` (no return: null)."""
    from schemas import encode
    from service.sim.wire import laser_scan

    return encode(laser_scan(s, stamp_ns))


@dataclass
class _Robot:
    robot_id: str
    truth: np.ndarray
    scans: list[bytes]
    odom: list[bytes]
    put_at: dict[int, float] = field(default_factory=dict)
    got_at: dict[int, float] = field(default_factory=dict)


class SteadyFleet:
    """Robots on a small simulated building, driven at 10 Hz on a thread of their own.

    Args:
        session: a Zenoh session on the service's bus.
        robots: how many.
        seconds: how long each can drive.
        map_id: the id their map is put under.
        seed: of the building, the paths and the scans.
    """

    def __init__(
        self,
        session: Any,
        robots: int = 3,
        seconds: float = 60.0,
        map_id: str = "m1",
        seed: int = 3,
    ) -> None:
        from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan
        from schemas import Map, Odometry, encode

        rng = np.random.default_rng(seed)
        self.session = session
        self.map_id = map_id
        self.world = make_building(rng)
        self.map_payload = encode(Map(map_id=map_id, version=1, geometry=self.world.to_geojson()))
        self.t0 = time.time_ns()
        steps = int(seconds * RATE_HZ)
        self.robots: list[_Robot] = []
        for i in range(robots):
            truth = make_trajectory(self.world, rng, steps, dt=1.0 / RATE_HZ)
            scans, odom = [], []
            for k in range(steps):
                s = simulate_scan(self.world, truth[k], LidarModel(beams=180), rng)
                stamp = self.stamp(k)
                scans.append(scan_payload(s, stamp))
                p = truth[k]
                odom.append(
                    encode(
                        Odometry(stamp_ns=stamp, x=float(p[0]), y=float(p[1]), theta=float(p[2]))
                    )
                )
            self.robots.append(_Robot(f"steady{i}", truth, scans, odom))
        self._by_id = {r.robot_id: r for r in self.robots}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sub: Any = None
        self.sent = 0

    def stamp(self, k: int) -> int:
        """The stamp of step ``k``, ns."""
        return self.t0 + int(k * 1e9 / RATE_HZ)

    def _on_pose(self, sample: Any) -> None:
        now = time.monotonic()
        p = json.loads(sample.payload.to_bytes())
        r = self._by_id.get(p["robot_id"])
        if r is not None:
            k = round((p["stamp_ns"] - self.t0) * RATE_HZ / 1e9)
            r.got_at.setdefault(k, now)

    def start(self) -> None:
        """Put the map, give every robot its initial pose, and start driving."""
        from schemas import InitialPose, encode

        s = self.session
        self._sub = s.declare_subscriber("rlutf/robots/*/pose", self._on_pose)
        s.put(f"rlutf/maps/{self.map_id}", self.map_payload, encoding=JSON_ENCODING)
        time.sleep(0.5)
        for r in self.robots:
            p = r.truth[0]
            s.put(f"rlutf/robots/{r.robot_id}/odom", r.odom[0], encoding=JSON_ENCODING)
            start = InitialPose(
                stamp_ns=self.stamp(0), map_id=self.map_id, x=p[0], y=p[1], theta=p[2]
            )
            s.put(f"rlutf/robots/{r.robot_id}/initialpose", encode(start))
        self._thread = threading.Thread(target=self._drive, name="steady-fleet", daemon=True)
        self._thread.start()

    def _drive(self) -> None:
        begin = time.monotonic()
        period = 1.0 / RATE_HZ
        steps = len(self.robots[0].scans)
        for k in range(1, steps):
            for j, r in enumerate(self.robots):
                delay = begin + (k + j / len(self.robots)) * period - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                self.session.put(
                    f"rlutf/robots/{r.robot_id}/odom", r.odom[k], encoding=JSON_ENCODING
                )
                r.put_at[k] = time.monotonic()
                self.session.put(
                    f"rlutf/robots/{r.robot_id}/scan", r.scans[k], encoding=JSON_ENCODING
                )
                self.sent += 1

    def wait_steady(self, timeout: float = 120.0) -> bool:
        """Wait until every robot had a pose for each of its last 20 scans (the service's
        workers have loaded their kernels and the robots' localizers are made)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if all(
                len(r.put_at) > 25 and all(k in r.got_at for k in sorted(r.put_at)[-25:-5])
                for r in self.robots
            ):
                return True
            time.sleep(0.1)
        return False

    def stop(self) -> None:
        """Stop driving (poses still in flight are counted for a moment)."""
        time.sleep(1.0)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self._sub is not None:
            self._sub.undeclare()

    def window(self, start: float, end: float) -> dict[str, float]:
        """The robots' poses over the scans put in ``[start, end)`` (``time.monotonic``).

        Returns:
            ``scans``, ``answered`` (share), ``max_gap_s`` (the longest time any robot went
            without a pose, from ``start`` to its last pose or ``end``), ``p50_ms``, ``p99_ms``
            and ``max_ms`` of the scan-to-pose latency.
        """
        lat: list[float] = []
        scans = answered = 0
        gap = 0.0
        for r in self.robots:
            last = start
            for k, put in sorted(r.put_at.items()):
                if not start <= put < end:
                    continue
                scans += 1
                got = r.got_at.get(k)
                if got is None:
                    continue
                answered += 1
                lat.append(got - put)
            arrivals = sorted(t for t in r.got_at.values() if start <= t < end + 1.0)
            for t in arrivals:
                gap = max(gap, t - last)
                last = t
            gap = max(gap, min(end, time.monotonic()) - last)
        q = np.percentile(lat, [50, 99, 100]) * 1e3 if lat else [math.nan] * 3
        return {
            "scans": scans,
            "answered": answered / scans if scans else math.nan,
            "max_gap_s": gap,
            "p50_ms": float(q[0]),
            "p99_ms": float(q[1]),
            "max_ms": float(q[2]),
        }


def process_rss_mb(pid: int | None = None) -> dict[int, float]:
    """Resident memory of a process and each of its descendants (:func:`bench.procstat.
    descendants`: a child between fork and exec left out), MB by pid (Linux)."""
    root = pid or os.getpid()
    out: dict[int, float] = {}
    for p in [root, *descendants(root)]:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    out[p] = int(line.split()[1]) / 1024.0
        except OSError:
            continue
    return out


def rss_mb(pid: int | None = None) -> float:
    """Resident memory of a process and all its descendants, MB (Linux)."""
    return sum(process_rss_mb(pid).values())


def process_role(pid: int, root: int) -> str:
    """What a process of a service's tree is, from its command line and its parent: ``host``
    (the process started), ``p1`` ... (the host's service processes), ``p1's child`` (a spawned
    helper of that one: a worker, the map checker, a kernel compiler)."""
    if pid == root:
        return "host"
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return f"pid {pid}"
    for arg in argv:
        name = Path(arg.decode(errors="replace")).name
        if name.startswith("process-") and name.endswith(".json"):
            return "p" + name[len("process-") : -len(".json")]
    return f"{process_role(parent, root)}'s child"


class PeakRss:
    """Samples the resident memory of a process tree every 50 ms on a thread: ``peak`` (the
    tree's, MB) and ``by_role`` (each process's peak, MB, by :func:`process_role`; the largest
    of several children of one role)."""

    def __init__(self, pid: int | None = None) -> None:
        self.pid = pid
        self.peak = 0.0
        self.phase = 0.0
        self.by_role: dict[str, float] = {}
        self._roles: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="peak-rss", daemon=True)

    def _sample(self) -> float:
        root = self.pid or os.getpid()
        each = process_rss_mb(root)
        for pid, mb in each.items():
            role = self._roles.get(pid)
            if role is None:
                role = self._roles[pid] = process_role(pid, root)
            self.by_role[role] = max(self.by_role.get(role, 0.0), mb)
        return sum(each.values())

    def _run(self) -> None:
        while not self._stop.is_set():
            now = self._sample()
            self.peak = max(self.peak, now)
            self.phase = max(self.phase, now)
            self._stop.wait(0.05)

    def restart(self) -> float:
        """The peak since the last restart (or the start), MB; starts a new one."""
        peak, self.phase = self.phase, 0.0
        return max(peak, rss_mb(self.pid))

    def __enter__(self) -> PeakRss:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.peak = max(self.peak, self._sample())


def square_map(map_id: str, side: float) -> bytes:
    """A Map of one empty square (issue 19: 144 bytes for 2 km)."""
    from schemas import Map, encode

    ring = [[0.0, 0.0], [side, 0.0], [side, side], [0.0, side], [0.0, 0.0]]
    return encode(
        Map(map_id=map_id, version=1, geometry={"type": "Polygon", "coordinates": [ring]})
    )


def wavy_room(vertices: int, radius: float = 6.0) -> dict[str, Any]:
    """A round room whose wall ripples (5 cm), drawn with ``vertices`` vertices (GeoJSON)."""
    t = np.linspace(0.0, 2.0 * math.pi, vertices, endpoint=False)
    r = radius + 0.05 * np.sin(t * 200.0)
    ring = np.column_stack([r * np.cos(t), r * np.sin(t)])
    ring = np.vstack([ring, ring[:1]])
    return {"type": "Polygon", "coordinates": [ring.tolist()]}
