"""Test harness: a real service and real Zenoh client sessions on loopback."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from rlutf.map import Map as World
from rlutf.sim import LidarModel, make_building
from schemas import InitialPose, LaserScan, Map, Odometry, encode
from service.config import Settings
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.recording import make_recorder
from service.sim.plan import RobotPlan, plan_robot
from service.sim.wire import laser_scan

JSON = zenoh.Encoding.APPLICATION_JSON


def wait_until(pred: Callable[[], object], timeout: float = 10.0, every: float = 0.05) -> bool:
    """Whether ``pred()`` came true within ``timeout`` seconds (looked at every ``every``)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(every)
    return bool(pred())


def health(client: zenoh.Session) -> dict[str, Any]:
    """The Health message of the service ``client`` reaches (the first to answer)."""
    reply = next(iter(client.get("rlutf/service/*/health", timeout=2.0)))
    return json.loads(reply.ok.payload.to_bytes())  # type: ignore[no-any-return]


@dataclass
class Collector:
    """Collects decoded JSON samples per key."""

    samples: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.setdefault(str(sample.key_expr), []).append(
                json.loads(sample.payload.to_bytes())
            )

    def on(self, key: str) -> list[dict[str, Any]]:
        with self.lock:
            return list(self.samples.get(key, []))

    def wait_for(self, pred: Callable[[], bool], timeout: float = 10.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred():
                return True
            time.sleep(0.02)
        return pred()


@dataclass
class SimRobot:
    """A simulated robot (:mod:`service.sim`'s plan, exact odometry) publishing on a session."""

    plan: RobotPlan
    session: zenoh.Session
    t0: int
    step: int = 0

    @property
    def robot_id(self) -> str:
        return self.plan.robot_id

    @property
    def truth(self) -> np.ndarray:
        return self.plan.truth

    def stamp(self, i: int) -> int:
        return self.t0 + i * 100_000_000

    def odom(self, i: int) -> None:
        x, y, theta = self.plan.odometry_at(i)
        msg = Odometry(stamp_ns=self.stamp(i), x=x, y=y, theta=theta)
        self.session.put(f"rlutf/robots/{self.robot_id}/odom", encode(msg), encoding=JSON)

    def initial_pose(self, map_id: str, offset: tuple[float, float, float] = (0, 0, 0)) -> None:
        p = self.truth[0]
        msg = InitialPose(
            stamp_ns=self.stamp(0),
            map_id=map_id,
            x=float(p[0] + offset[0]),
            y=float(p[1] + offset[1]),
            theta=float(p[2] + offset[2]),
        )
        self.odom(0)
        self.session.put(f"rlutf/robots/{self.robot_id}/initialpose", encode(msg), encoding=JSON)

    def scan_msg(self, i: int) -> LaserScan:
        return laser_scan(self.plan.scans[self.plan.index(i)], self.stamp(i))

    def advance(self) -> int:
        """Publish the next odometry and scan; returns the step index."""
        self.step += 1
        self.odom(self.step)
        self.session.put(
            f"rlutf/robots/{self.robot_id}/scan", encode(self.scan_msg(self.step)), encoding=JSON
        )
        return self.step


def sim_robot(
    robot_id: str,
    world: World,
    seed: int,
    session: zenoh.Session,
    steps: int = 200,
    t0: int | None = None,
) -> SimRobot:
    """A robot on its own path of ``steps`` poses (seeded), 180-beam scans, stamps from ``t0``
    (default: now) at 10 Hz."""
    start = time.time_ns() if t0 is None else t0  # before the drawing: no stamp ahead of now
    plan = plan_robot(robot_id, world, np.random.default_rng(seed), steps, LidarModel(beams=180))
    return SimRobot(plan, session, start)


@dataclass
class Bench:
    """A running service and an operator client session."""

    service: LocalizationService
    client: zenoh.Session
    endpoint: str
    world: World
    store: Path

    def put_map(self, map_id: str = "m1", version: int = 1, world: World | None = None) -> None:
        w = world or self.world
        self.client.put(
            f"rlutf/maps/{map_id}",
            encode(Map(map_id=map_id, version=version, geometry=w.to_geojson())),
            encoding=JSON,
        )

    def robot(self, robot_id: str, seed: int, steps: int = 200) -> SimRobot:
        return sim_robot(robot_id, self.world, seed, self.client, steps)


def drive(bench: Bench, robot_ids: list[str], steps: int) -> dict[str, dict[str, Any]]:
    """Put map m1, place each robot on it and feed it ``steps`` scans, until each one's last
    pose is out; the last pose each robot got (decoded JSON), by robot id."""
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/*/pose", col)
    bench.put_map()
    time.sleep(0.3)
    robots = [bench.robot(r, seed) for seed, r in enumerate(robot_ids, 1)]
    for r in robots:
        r.initial_pose("m1")
    time.sleep(0.3)
    for _ in range(steps):
        for r in robots:
            r.advance()
        time.sleep(0.03)
    for r in robots:
        key, last = f"rlutf/robots/{r.robot_id}/pose", r.stamp(r.step)
        assert col.wait_for(lambda k=key, s=last: any(p["stamp_ns"] == s for p in col.on(k)))
    sub.undeclare()
    return {r.robot_id: col.on(f"rlutf/robots/{r.robot_id}/pose")[-1] for r in robots}


WORLD = make_building(np.random.default_rng(11))


def start_service(store: Path, port: int, workers: int = 0, **kw: Any) -> LocalizationService:
    values: dict[str, Any] = {
        "listen": [f"tcp/127.0.0.1:{port}"],
        "store_dir": store,
        "no_record": True,
        "workers": workers,
        "instance": f"test-{port}",
        "event_interval_s": 0.0,
    }
    settings = Settings(**{**values, **kw})
    recorder = None if settings.no_record else make_recorder(settings)
    return LocalizationService(settings, recorder=recorder).start()


@contextmanager
def running_bench(tmp_path: Path, **kw: Any) -> Iterator[Bench]:
    """A service (settings ``kw`` over the test defaults) and a client session to it."""
    port = free_port()
    service = start_service(tmp_path / "store", port, **kw)
    endpoint = f"tcp/127.0.0.1:{port}"
    client = zenoh.open(client_config(endpoint))
    try:
        yield Bench(service, client, endpoint, WORLD, tmp_path / "store")
    finally:
        client.close()
        service.close()


def storeless_service(
    bench: Bench, instance: str = "second", **settings: Any
) -> LocalizationService:
    """A second service on ``bench``'s bus, a client of it with no store, log or pose state: as
    the processes of `rlutf serve --processes N` but the host's, or an instance started with
    --no-store. Started; the caller closes it."""
    base: dict[str, Any] = {
        "mode": "client",
        "connect": [bench.endpoint],
        "no_store": True,
        "no_record": True,
        "no_state": True,
        "workers": 0,
        "instance": instance,
    }
    return LocalizationService(Settings(**(base | settings))).start()
