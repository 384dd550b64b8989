"""``rlutf serve --processes 2``: a host of two service processes behind one router and store.

A real host process (router, map store, supervision, merged Health and metrics) and its two
service processes, a simulated fleet over loopback, a SIGKILL of one process, and the audit of
every log the processes wrote.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import zenoh
from scaleout_harness import Driver, PoseLog, make_fleet, wait_until
from service_harness import WORLD

from schemas import Map, encode
from service.cluster.membership import assign
from service.live.host import (
    FOLDER_PREFIX,
    merged_extra,
    process_name,
    settings_folder,
    sweep_folders,
)
from service.live.robots import fetch_robots, merge_robots
from service.live.sessions import client_config, free_port
from service.logs.replay import replay
from service.logs.runs import group_runs

JSON = zenoh.Encoding.APPLICATION_JSON
NAMES = [process_name("h", 0), process_name("h", 1)]


def _health(session: zenoh.Session, name: str) -> dict[str, Any]:
    for r in session.get(f"rlutf/service/{name}/health", timeout=2.0):
        if r.ok is not None:
            return dict(json.loads(r.ok.payload.to_bytes()))
    return {}


def _owned(host: dict[str, Any]) -> dict[str, list[str]]:
    by = host.get("extra", {}).get("by_process", {})
    return {n: sorted(by.get(n, {}).get("extra", {}).get("owned", [])) for n in NAMES}


def _dist(pose: dict[str, Any], truth: Any) -> float:
    return math.hypot(pose["x"] - truth[0], pose["y"] - truth[1])


@pytest.mark.integration
def test_a_host_of_two_processes_serves_a_fleet_through_a_kill(tmp_path: Path) -> None:
    """Asserted: the host is ready only with both processes, and its Health adds theirs up,
    its robot view lists every robot and its MapHealth covers every robot's scans;
    the two processes (the first in the host's own process) split the robots as rendezvous
    hashing over their names says; when the other is SIGKILLed, each of its robots is served
    again by the first within 2 s of its last pose, within 5 cm of the truth, and the host
    starts the process again, which takes its robots back; the host's metrics endpoint serves
    both processes' series; SIGTERM stops everything with exit code 0; and every run the
    processes' logs hold replays bit for bit.
    """
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    metrics = free_port()
    out = (tmp_path / "host.log").open("wb")
    cmd = [sys.executable, "-m", "service", "serve", "--processes", "2", "--instance", "h"]
    cmd += ["--listen", endpoint, "--store", str(tmp_path / "store")]
    cmd += ["--state", str(tmp_path / "state"), "--record", str(tmp_path / "logs")]
    cmd += ["--metrics-port", str(metrics), "--metrics-addr", "127.0.0.1"]
    host = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    session: zenoh.Session | None = None
    driver: Driver | None = None
    poses = PoseLog()

    def text() -> str:
        return (tmp_path / "host.log").read_text()[-3000:]

    try:
        end = time.monotonic() + 300
        while session is None and time.monotonic() < end and host.poll() is None:
            try:
                session = zenoh.open(client_config(endpoint))
            except zenoh.ZError:
                time.sleep(0.2)
        assert session is not None, text()
        assert wait_until(lambda: _health(session, "h").get("ready") is True, 300, 0.2), text()
        first = _health(session, "h")
        assert first["extra"]["host"] is True
        assert {p["name"] for p in first["extra"]["processes"]} == set(NAMES)
        sub = session.declare_subscriber("rlutf/robots/*/pose", poses)
        health_puts: list[bytes] = []
        health_sub = session.declare_subscriber(
            "rlutf/maphealth/*", lambda s: health_puts.append(s.payload.to_bytes())
        )
        world = Map(map_id="m1", version=1, geometry=WORLD.to_geojson())
        session.put("rlutf/maps/m1", encode(world), encoding=JSON)
        assert wait_until(
            lambda: all("m1" in _health(session, n).get("extra", {}).get("maps", [])
                        for n in NAMES), 20.0)  # fmt: skip
        fleet = make_fleet(session, WORLD, 8, 400)
        robots = [r.robot_id for r in fleet]
        for r in fleet:
            r.initial_pose("m1")
        driver = Driver(fleet).start()
        time.sleep(3.0)
        split = assign(robots, NAMES)
        expected = {n: sorted(r for r in robots if split[r] == n) for n in NAMES}
        assert wait_until(lambda: _owned(_health(session, "h")) == expected, 5.0), text()
        assert all(expected.values())
        # the per-robot view (rlutf robots) lists every robot, each by its process
        assert wait_until(
            lambda: {s.robot_id: s.owner for s in merge_robots(fetch_robots(session, "rlutf", 2))}
            == split, 10.0), text()  # fmt: skip
        assert wait_until(lambda: len(health_puts) >= 2, 20.0), text()
        # one MapHealth of the whole fleet, from one process: each shares its robots' evidence
        # and merges the other's (service.evidence), and one of them puts the map's report
        fleet_seen = lambda: [json.loads(p)["robots"] for p in health_puts]  # noqa: E731
        assert wait_until(lambda: fleet_seen()[-1] == len(robots), 20.0), (fleet_seen(), text())
        assert fleet_seen() == sorted(fleet_seen()), fleet_seen()  # not two reports in turn
        time.sleep(1.5)  # the Health the host polls is a second old at most
        both = _health(session, "h")
        parts = both["extra"]["by_process"]
        assert both["processed"] == sum(parts[n]["processed"] for n in NAMES) > 0
        # each process's MapHealth puts reach the other, which takes them for what they are
        assert both["rejected"] == 0, parts

        body = urllib.request.urlopen(f"http://127.0.0.1:{metrics}/metrics", timeout=10).read()
        exposition = body.decode()
        assert "rlutf_host_processes_scraped 2.0" in exposition
        for name in NAMES:
            assert f'rlutf_poses_published_total{{instance="{name}",status=' in exposition

        victim = NAMES[1]  # process 0 is the host itself
        assert next(p["pid"] for p in both["extra"]["processes"] if p["name"] == NAMES[0]) == (
            host.pid
        )
        pid = next(p["pid"] for p in both["extra"]["processes"] if p["name"] == victim)
        t_kill = time.monotonic()
        subprocess.run(["kill", "-9", str(pid)], check=True)
        time.sleep(4.0)
        moved = expected[victim]
        # started again, ready, and the robots back where rendezvous puts them
        assert wait_until(
            lambda: any(p["name"] == victim and p["restarts"] == 1 and p["alive"]
                        for p in _health(session, "h")["extra"]["processes"])
            and _owned(_health(session, "h")) == expected, 60.0, 0.2), text()  # fmt: skip
        time.sleep(2.0)
        driver.stop()
        t_stop = time.monotonic()
        sub.undeclare()
        health_sub.undeclare()
        host.send_signal(signal.SIGTERM)
        assert host.wait(30) == 0, text()
    finally:
        if driver is not None:
            driver.stop()
        if host.poll() is None:
            host.kill()
            host.wait()
        if session is not None:
            session.close()
        out.close()

    truth = {r.robot_id: r.truth for r in fleet}
    t0 = fleet[0].t0
    for robot in robots:
        rows = poses.of(robot)
        times = [t for t, _ in rows]
        assert times[-1] > t_stop - 1.0, robot
        assert max(b - a for a, b in itertools.pairwise(times)) < 2.0, robot
        late = [p for t, p in rows if t > t_kill]
        assert late, robot
        step = lambda p: int(p["stamp_ns"] - t0) // 100_000_000  # noqa: E731
        assert all(_dist(p, truth[robot][step(p)]) < 0.05 for p in late), robot
    assert moved

    files = sorted((tmp_path / "logs").glob("*.mcap"))
    runs = group_runs(files)
    # the survivor's run and the restarted process's (the killed run's file is unfinished)
    assert {run.instance for run in runs} == set(NAMES)
    for run in runs:
        result = replay(list(run.files), foxglove=False)
        assert result.recorded
        for robot, recorded in result.recorded.items():
            assert [p.payload for p in result.recomputed[robot]] == [p.payload for p in recorded]


def test_the_host_adds_its_processes_figures_up() -> None:
    merged = merged_extra(
        [
            {"lost": 1, "compute_ms": {"p99": 2.0}, "maps": ["a"], "ready": True},
            {"lost": 2, "compute_ms": {"p99": 5.0}, "maps": ["b"], "ready": True},
        ]
    )
    assert merged == {"lost": 3, "compute_ms": {"p99": 5.0}}


def test_settings_folders_of_hosts_that_are_gone_are_removed(tmp_path: Path) -> None:
    """A host killed by SIGKILL leaves its folder of settings files; the next host removes it,
    and nothing of a host that runs or of another program."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # its pid is no longer running (reused only after a wrap of the pid space)
    dead = tmp_path / f"{FOLDER_PREFIX}{gone.pid}-abcd1234"
    live = tmp_path / f"{FOLDER_PREFIX}{os.getpid()}-abcd1234"
    older = tmp_path / f"{FOLDER_PREFIX}abcd1234"  # named before the pid was in the name
    other = tmp_path / "rlutf-host-notes-1"
    for folder in (dead, live, older, other):
        folder.mkdir()
        (folder / "process-1.json").write_text("{}")
    assert sweep_folders(tmp_path) == [dead]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        p.name for p in (live, older, other)
    )
    with settings_folder() as made:
        assert Path(made).name.startswith(f"{FOLDER_PREFIX}{os.getpid()}-")


def test_the_host_tunes_its_own_processes_garbage_collection(tmp_path: Path) -> None:
    """The host's own service process (the only one with ``--processes 1``) freezes its start-up
    objects out of collections and collects less often, as every other service process does:
    without it, at 200 robots a full collection held its robots up for about 0.1 s."""
    log_path = tmp_path / "host.log"
    cmd = [sys.executable, "-m", "service", "serve", "--processes", "1", "--instance", "g"]
    cmd += ["--listen", f"tcp/127.0.0.1:{free_port()}", "--store", str(tmp_path / "store")]
    cmd += ["--state", str(tmp_path / "state"), "--no-record", "--log-level", "DEBUG"]
    with log_path.open("wb") as out:
        host = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        try:
            tuned = wait_until(lambda: "garbage collection tuned" in log_path.read_text(), 300, 0.2)
            assert tuned, log_path.read_text()[-3000:]
            host.send_signal(signal.SIGTERM)
            assert host.wait(30) == 0, log_path.read_text()[-3000:]
        finally:
            if host.poll() is None:
                host.kill()
                host.wait()
    line = next(s for s in log_path.read_text().splitlines() if "garbage collection tuned" in s)
    frozen = int(line.split("tuned: ")[1].split()[0])
    assert frozen > 10_000  # the modules, the settings and the service's start-up objects
