"""Harness of the scale-out tests: a router in the test process, service subprocesses, a fleet."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from service_harness import JSON, SimRobot, sim_robot

from rlutf.map import Map as World
from schemas import Map, encode
from service.keys import Keys
from service.live.sessions import session_config
from service.maps.files import FileMapStore
from service.maps.store import MapStorage


def router_config(port: int) -> zenoh.Config:
    """An in-process Zenoh router on 127.0.0.1:port, no scouting."""
    return session_config("router", listen=[f"tcp/127.0.0.1:{port}"])


def wait_until(pred: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    """Poll ``pred`` until it holds or ``timeout`` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return pred()


@dataclass
class Instance:
    """One ``rlutf serve`` subprocess in client mode."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it does not stop within 5 s."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5.0)


def spawn_instance(endpoint: str, name: str, log_dir: Path) -> Instance:
    """Start ``python -m service serve --mode client ...`` connected to ``endpoint``.

    It records its MCAP logs into ``log_dir / f"rec-{name}"``.
    """
    log = log_dir / f"{name}.log"
    cmd = [
        sys.executable,
        "-m",
        "service",
        "--log-level",
        "INFO",
        "serve",
        "--mode",
        "client",
        "--connect",
        endpoint,
        "--no-store",
        "--state",  # each instance its own, in the test's folder (not the working directory)
        str(log_dir / f"state-{name}"),
        "--record",
        str(log_dir / f"rec-{name}"),
        "--workers",
        "0",
        "--instance",
        name,
    ]
    with log.open("wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    return Instance(name, proc, log)


def live_members(session: zenoh.Session) -> set[str]:
    """Instance names whose liveliness token is visible."""
    head = "rlutf/service/"
    return {
        str(r.ok.key_expr)[len(head) :]
        for r in session.liveliness().get("rlutf/service/*", timeout=2.0)
        if r.ok is not None
    }


def health(session: zenoh.Session, name: str) -> dict[str, Any] | None:
    """One instance's Health message, or ``None`` if it does not answer."""
    for r in session.get(Keys().health(name), timeout=2.0):
        if r.ok is not None:
            return dict(json.loads(r.ok.payload.to_bytes()))
    return None


@dataclass
class PoseLog:
    """Every pose put on the bus, with its receive time (monotonic seconds)."""

    rows: list[tuple[str, float, dict[str, Any]]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        robot = str(sample.key_expr).split("/")[2]
        pose = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.rows.append((robot, time.monotonic(), pose))

    def of(self, robot: str) -> list[tuple[float, dict[str, Any]]]:
        """A robot's poses in receive order."""
        with self.lock:
            return [(t, p) for r, t, p in self.rows if r == robot]


@dataclass
class Router:
    """The test's Zenoh router session, hosting the map storage."""

    session: zenoh.Session
    storage: MapStorage
    endpoint: str

    @classmethod
    def open(cls, port: int, store: Path) -> Router:
        """Open the router and its file-backed map storage."""
        session = zenoh.open(router_config(port))
        storage = MapStorage(session, Keys(), FileMapStore(store), 1_000_000)
        return cls(session, storage, f"tcp/127.0.0.1:{port}")

    def put_map(self, world: World, map_id: str = "m1") -> None:
        """Put version 1 of ``map_id``."""
        msg = Map(map_id=map_id, version=1, geometry=world.to_geojson())
        self.session.put(f"rlutf/maps/{map_id}", encode(msg), encoding=JSON)

    def close(self) -> None:
        """Close the storage and the session."""
        self.storage.close()
        self.session.close()


def make_fleet(session: zenoh.Session, world: World, count: int, steps: int) -> list[SimRobot]:
    """``count`` simulated robots on their own paths, stamps from now at 10 Hz."""
    t0 = time.time_ns()
    return [sim_robot(f"r{i}", world, 100 + i, session, steps, t0) for i in range(count)]


class Driver:
    """Drives a fleet at 10 Hz on a thread: every tick, each robot's odometry then its scan."""

    def __init__(self, fleet: list[SimRobot], period: float = 0.1) -> None:
        self.fleet = fleet
        self.period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fleet", daemon=True)

    def start(self) -> Driver:
        """Start ticking."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop after the current tick."""
        self._stop.set()
        self._thread.join(5.0)

    def _run(self) -> None:
        steps = min(len(r.truth) for r in self.fleet) - 1
        next_tick = time.monotonic()
        while not self._stop.is_set() and self.fleet[0].step < steps:
            for robot in self.fleet:
                robot.advance()
            next_tick += self.period
            self._stop.wait(max(next_tick - time.monotonic(), 0.0))
