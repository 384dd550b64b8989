"""Restarts without losing a robot (issue 15): the durable pose state over real sessions.

A service tracks simulated robots, then stops (orderly, or ``kill -9`` of a real ``rlutf serve``);
the robots drive on while it is down. A new service on the same store and state folder resumes
every robot from its last published pose at the robot's next input, with no InitialPose: its
first pose comes within 2 s of the robot's next scan and within a few centimetres of the truth,
because the odometry reading kept beside the pose carries the motion made during the downtime.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from scaleout_harness import PoseLog, wait_until
from service_harness import JSON, WORLD, Collector, SimRobot, sim_robot, start_service

from schemas import Map, encode
from service.cluster.posestate import FILE_NAME
from service.live.sessions import client_config, free_port

pytestmark = pytest.mark.integration

#: Steps the robots drive while the service is down (0.1 s each, 1.2 m): farther than the first
#: update's wide search reaches (0.5 m), so only the odometry kept in the state can carry it.
DOWNTIME_STEPS = 15


def _fleet(session: zenoh.Session, count: int) -> list[SimRobot]:
    t0 = time.time_ns()
    return [sim_robot(f"r{i}", WORLD, 40 + i, session, 200, t0) for i in range(count)]


def _drive(fleet: list[SimRobot], steps: int, sent: dict[str, float] | None = None) -> None:
    """``steps`` ticks at 10 Hz; ``sent``: monotonic time of each robot's first scan put."""
    for _ in range(steps):
        for robot in fleet:
            robot.advance()
            if sent is not None:
                sent.setdefault(robot.robot_id, time.monotonic())
        time.sleep(0.1)


def _track(client: zenoh.Session, fleet: list[SimRobot]) -> None:
    """Put the map, place the robots, drive until each is tracked close to the truth."""
    poses = PoseLog()
    sub = client.declare_subscriber("rlutf/robots/*/pose", poses)
    msg = Map(map_id="m1", version=1, geometry=WORLD.to_geojson())
    client.put("rlutf/maps/m1", encode(msg), encoding=JSON)
    time.sleep(0.5)
    for robot in fleet:
        robot.initial_pose("m1")
    time.sleep(0.3)
    _drive(fleet, 15)
    for robot in fleet:
        assert wait_until(lambda r=robot: _last_error(poses, r) < 0.05, 5.0), robot.robot_id
    sub.undeclare()


def _at(robot: SimRobot, pose: dict[str, Any]) -> np.ndarray:
    return robot.truth[(pose["stamp_ns"] - robot.t0) // 100_000_000]


def _error(robot: SimRobot, pose: dict[str, Any]) -> float:
    truth = _at(robot, pose)
    return math.hypot(pose["x"] - truth[0], pose["y"] - truth[1])


def _last_error(poses: PoseLog, robot: SimRobot) -> float:
    rows = poses.of(robot.robot_id)
    return _error(robot, rows[-1][1]) if rows else math.inf


def _resumed(
    fleet: list[SimRobot], poses: PoseLog, sent: dict[str, float]
) -> dict[str, tuple[float, float]]:
    """Per robot: seconds from its first scan after the restart to its first pose, and the
    error of that pose (m)."""
    out = {}
    for robot in fleet:
        first = poses.of(robot.robot_id)[0]
        out[robot.robot_id] = (first[0] - sent[robot.robot_id], _error(robot, first[1]))
    return out


def _subscribe(client: zenoh.Session, poses: PoseLog, events: Collector) -> list[Any]:
    return [
        client.declare_subscriber("rlutf/robots/*/pose", poses),
        client.declare_subscriber("rlutf/**/events", events),
    ]


def _codes(events: Collector, robot: str) -> list[str]:
    return [e["code"] for e in events.on(f"rlutf/robots/{robot}/events")]


def _health(client: zenoh.Session) -> dict[str, Any]:
    replies = [r.ok for r in client.get("rlutf/service/*/health", timeout=2.0) if r.ok]
    assert len(replies) == 1
    return dict(json.loads(replies[0].payload.to_bytes())["extra"])


def test_an_orderly_restart_resumes_every_robot(tmp_path: Path) -> None:
    port, store = free_port(), tmp_path / "store"
    endpoint = f"tcp/127.0.0.1:{port}"
    service = start_service(store, port)
    client = zenoh.open(client_config(endpoint))
    fleet = _fleet(client, 3)
    try:
        _track(client, fleet)
    finally:
        client.close()
        service.close()  # orderly: the final snapshot is written
    doc = json.loads((store / "state" / FILE_NAME).read_bytes())
    assert sorted(doc["robots"]) == ["r0", "r1", "r2"]
    for robot in fleet:  # the robots drive on while the service is down
        robot.step += DOWNTIME_STEPS

    service = start_service(store, port)
    client = zenoh.open(client_config(endpoint))
    try:
        # Before any robot sends a thing, the service shows and answers what it holds of them
        # (it listed none: an operator checking parked robots after a restart saw no robot).
        last = {robot: entry["pose"] for robot, entry in doc["robots"].items()}
        view: dict[str, Any] = {}
        for _ in range(50):
            (reply,) = [r.ok for r in client.get("rlutf/service/*/robots", timeout=2.0) if r.ok]
            view = json.loads(reply.payload.to_bytes())
            if len(view["robots"]) == 3:
                break
            time.sleep(0.1)
        assert [(r["robot_id"], r["x"], r["y"]) for r in view["robots"]] == [
            (r, last[r]["x"], last[r]["y"]) for r in ("r0", "r1", "r2")
        ]
        assert all(r["age_s"] > 0 and r["latency_ms"] is None for r in view["robots"])
        answered = [json.loads(r.ok.payload.to_bytes()) for r in client.get("rlutf/robots/r1/pose")]
        assert [(a["robot_id"], a["stamp_ns"]) for a in answered] == [
            ("r1", last["r1"]["stamp_ns"])
        ]
        _assert_every_robot_resumes(client, fleet, "orderly restart")
    finally:
        client.close()
        service.close()


def test_a_pose_older_than_the_limit_is_relocalized_instead(tmp_path: Path) -> None:
    port, store = free_port(), tmp_path / "store"
    endpoint = f"tcp/127.0.0.1:{port}"
    service = start_service(store, port)
    client = zenoh.open(client_config(endpoint))
    fleet = _fleet(client, 1)
    try:
        _track(client, fleet)
    finally:
        client.close()
        service.close()
    time.sleep(1.2)  # down longer than the limit below
    service = start_service(store, port, resume_max_age_s=1.0)
    client = zenoh.open(client_config(endpoint))
    try:
        poses, events = PoseLog(), Collector()
        subs = _subscribe(client, poses, events)
        robot = fleet[0]
        robot.session = client
        _drive(fleet, 3)
        assert wait_until(lambda: "relocalizing" in _codes(events, "r0"), 5.0)
        for _ in range(30):
            _drive(fleet, 1)
            if "relocalized" in _codes(events, "r0"):
                break
        codes = _codes(events, "r0")
        assert codes.index("relocalizing") < codes.index("relocalized"), codes
        assert poses.of("r0")[0][1]["status"] != "tracking"  # found by a search, not seeded
        _drive(fleet, 2)
        assert wait_until(lambda: _last_error(poses, robot) < 0.05, 5.0)
        assert poses.of("r0")[-1][1]["status"] != "lost"
        extra = _health(client)
        assert (extra["resumed"], extra["resumed_relocalize"]) == (1, 1)
        for s in subs:
            s.undeclare()
    finally:
        client.close()
        service.close()


@contextmanager
def _serve(endpoint: str, store: Path, state: Path, log: Path) -> Iterator[subprocess.Popen[bytes]]:
    env = {**os.environ, "RLUTF_EVENT_INTERVAL_S": "0"}
    env.pop("RLUTF_SETTINGS", None)
    cmd = [sys.executable, "-m", "service", "--log-level", "INFO", "serve", "--listen", endpoint]
    cmd += ["--store", str(store), "--state", str(state), "--no-record", "--workers", "0"]
    with log.open("ab") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def _client(endpoint: str, proc: subprocess.Popen[bytes]) -> zenoh.Session:
    """A client session once the service is up (its liveliness token is visible)."""
    end = time.monotonic() + 30
    while True:
        try:
            session = zenoh.open(client_config(endpoint))
            if list(session.liveliness().get("rlutf/service/*", timeout=1.0)):
                return session
            session.close()
        except zenoh.ZError:
            pass
        assert proc.poll() is None and time.monotonic() < end, "the service did not come up"
        time.sleep(0.1)


def test_kill_9_and_restart_resumes_every_robot(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    store, state, log = tmp_path / "store", tmp_path / "state", tmp_path / "serve.log"
    with _serve(endpoint, store, state, log) as proc:
        client = _client(endpoint, proc)
        fleet = _fleet(client, 3)
        try:
            _track(client, fleet)
            time.sleep(1.5)  # at least one snapshot after the last poses (state_interval_s 1)
        finally:
            client.close()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    assert sorted(json.loads((state / FILE_NAME).read_bytes())["robots"]) == ["r0", "r1", "r2"]
    for robot in fleet:
        robot.step += DOWNTIME_STEPS

    with _serve(endpoint, store, state, log) as proc:
        client = _client(endpoint, proc)
        try:
            _assert_every_robot_resumes(client, fleet, "kill -9 and restart")
        finally:
            client.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(15)


def test_a_corrupt_state_file_is_reported_and_the_service_runs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    store = tmp_path / "store"
    (store / "state").mkdir(parents=True)
    (store / "state" / FILE_NAME).write_bytes(b'{"version": 1, "robots": {"r0": {"po')
    port = free_port()
    caplog.set_level("WARNING", logger="service.live.publishing")
    service = start_service(store, port)  # the Event goes out before any client can hear it
    events = [r.getMessage() for r in caplog.records if r.name == "service.live.publishing"]
    assert any(m.startswith("state_unreadable rlutf/events") for m in events), events
    try:
        with zenoh.open(client_config(f"tcp/127.0.0.1:{port}")) as client:
            fleet = _fleet(client, 1)
            _track(client, fleet)  # the service runs as if it had no state
        assert json.loads(service.health())["extra"]["resumed"] == 0
    finally:
        service.close()
    doc = json.loads((store / "state" / FILE_NAME).read_bytes())
    assert list(doc["robots"]) == ["r0"]  # replaced by a good snapshot


def _assert_every_robot_resumes(client: zenoh.Session, fleet: list[SimRobot], what: str) -> None:
    """The robots drive on with no InitialPose: each gets a pose within 2 s of its next scan,
    within 5 cm of the truth, and the service counts them as resumed from the state."""
    poses, events = PoseLog(), Collector()
    subs = _subscribe(client, poses, events)
    sent: dict[str, float] = {}
    for robot in fleet:
        robot.session = client  # the robots reconnect
    _drive(fleet, 10, sent)
    assert wait_until(lambda: all(len(poses.of(r.robot_id)) >= 8 for r in fleet), 5.0)
    resumed = _resumed(fleet, poses, sent)
    print(f"{what}: seconds to first pose, error (m):", resumed)
    for robot_id, (seconds, error) in resumed.items():
        assert seconds < 2.0, robot_id
        assert error < 0.05, robot_id
    for robot in fleet:
        assert _last_error(poses, robot) < 0.05
        assert "not_initialized" not in _codes(events, robot.robot_id)
    extra = _health(client)
    assert (extra["resumed"], extra["resumed_relocalize"]) == (len(fleet), 0)
    for s in subs:
        s.undeclare()
