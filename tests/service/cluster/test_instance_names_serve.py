"""Instance names with ``rlutf serve`` processes: two of one name never both run.

A second instance of a live name refuses to start; two started together leave one; two that
ran apart on the two sides of a network partition meet when it heals, and the younger stops
(an Event, exit 1) while the older keeps its robots; a restarted instance whose predecessor's
tokens are still on the bus (a frozen process, until Zenoh's lease ends) waits for them and
starts. The claims themselves: ``test_instance_names.py``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import zenoh
from scaleout_harness import (
    Driver,
    Instance,
    PoseLog,
    Router,
    health,
    live_members,
    make_fleet,
    spawn_instance,
    wait_until,
)
from service_harness import WORLD, Collector

from service.keys import Keys
from service.live.sessions import client_config, free_port, session_config
from service.maps.files import FileMapStore
from service.maps.store import MapStorage

pytestmark = pytest.mark.integration


def _exit_code(instance: Instance, timeout: float) -> int | None:
    try:
        return instance.process.wait(timeout)
    except subprocess.TimeoutExpired:
        return None  # still running


def _claim(session: zenoh.Session, name: str) -> dict[str, Any]:
    """The claim an instance's Health states (``extra.claim``), empty if it does not answer."""
    return dict(((health(session, name) or {}).get("extra") or {}).get("claim") or {})


def test_a_second_instance_of_a_live_name_refuses_to_start(tmp_path: Path) -> None:
    """A second ``rlutf serve --instance i1`` exits 1 saying why, records nothing, and the
    first keeps its name and its robots."""
    router = Router.open(free_port(), tmp_path / "store")
    (tmp_path / "first").mkdir()
    (tmp_path / "second").mkdir()
    first = spawn_instance(router.endpoint, "i1", tmp_path / "first")
    second = None
    try:
        assert wait_until(lambda: live_members(router.session) == {"i1"}, 25.0), (
            first.log.read_text()[-2000:]
        )
        second = spawn_instance(router.endpoint, "i1", tmp_path / "second")
        code = _exit_code(second, 45.0)
        text = second.log.read_text()
        assert code == 1, text[-2000:]
        assert "each instance needs a name of its own" in text, text[-2000:]
        assert not list((tmp_path / "second" / "rec-i1").glob("*.mcap*"))
        assert first.process.poll() is None
        assert live_members(router.session) == {"i1"}
    finally:
        if second is not None:
            second.stop()
        first.stop()
        router.close()


def test_two_instances_of_one_name_started_together_leave_one(tmp_path: Path) -> None:
    """Two ``rlutf serve --instance b`` started at once: one exits 1 saying why, having
    recorded nothing; the other runs on as b, the only one that answers as b."""
    router = Router.open(free_port(), tmp_path / "store")
    folders = [tmp_path / "one", tmp_path / "two"]
    for folder in folders:
        folder.mkdir()
    both = [spawn_instance(router.endpoint, "b", folder) for folder in folders]
    try:
        end = time.monotonic() + 45.0
        while all(i.process.poll() is None for i in both) and time.monotonic() < end:
            time.sleep(0.1)
        codes = [i.process.poll() for i in both]
        texts = [i.log.read_text()[-2000:] for i in both]
        assert sorted(codes, key=str) == [1, None], (codes, texts)
        gone = codes.index(1)
        assert "each instance needs a name of its own" in texts[gone], texts[gone]
        assert not list((folders[gone] / "rec-b").glob("*.mcap*"))
        time.sleep(2.0)  # the other is not stopped later either
        assert both[1 - gone].process.poll() is None, texts[1 - gone]
        assert live_members(router.session) == {"b"}
        answers = [r.ok for r in router.session.get(Keys().health("b"), timeout=2.0) if r.ok]
        assert len(answers) == 1
    finally:
        for instance in both:
            instance.stop()
        router.close()


def test_a_healed_partition_stops_the_younger_instance_and_leaves_the_other_its_robots(
    tmp_path: Path,
) -> None:
    """Two routers, each with an instance b, that see each other only once a third router they
    both connect to comes up (a network partition healing). The older b localizes a fleet
    meanwhile; the younger, started alone on its side, started. Once they meet, the younger
    publishes an Event ``instance_name_taken`` (saying what it did) and exits 1, saying
    how to name it; the older runs on, its robots answered once a scan as before."""
    ports = [free_port() for _ in range(3)]
    ends = [f"tcp/127.0.0.1:{p}" for p in ports]
    near = zenoh.open(session_config("router", listen=[ends[0]], connect=[ends[2]]))
    storage = MapStorage(near, Keys(), FileMapStore(tmp_path / "store"), 1_000_000)
    router = Router(near, storage, ends[0])
    far = zenoh.open(session_config("router", listen=[ends[1]], connect=[ends[2]]))
    events = Collector()
    watched = far.declare_subscriber("rlutf/events", events)
    poses = PoseLog()
    followed = near.declare_subscriber("rlutf/robots/*/pose", poses)
    (tmp_path / "older").mkdir()
    (tmp_path / "younger").mkdir()
    older = spawn_instance(ends[0], "b", tmp_path / "older")
    younger: Instance | None = None
    bridge: zenoh.Session | None = None
    driver: Driver | None = None
    try:
        assert wait_until(lambda: live_members(near) == {"b"}, 25.0), older.log.read_text()
        kept = _claim(near, "b")
        router.put_map(WORLD)
        assert wait_until(
            lambda: "m1" in ((health(near, "b") or {}).get("extra") or {}).get("maps", []), 10.0
        )
        fleet = make_fleet(near, WORLD, 3, 400)
        robots = [r.robot_id for r in fleet]
        for robot in fleet:
            robot.initial_pose("m1")
        driver = Driver(fleet).start()
        assert wait_until(lambda: all(len(poses.of(r)) > 10 for r in robots), 15.0)
        younger = spawn_instance(ends[1], "b", tmp_path / "younger")
        assert wait_until(lambda: live_members(far) == {"b"}, 25.0), younger.log.read_text()
        assert younger.process.poll() is None and live_members(near) == {"b"}  # apart
        bridge = zenoh.open(session_config("router", listen=[ends[2]]))
        code = _exit_code(younger, 30.0)
        t_gone = time.monotonic()
        text = younger.log.read_text()
        assert code == 1, text[-3000:]
        assert "another instance named b is running" in text, text[-3000:]
        assert "this instance stops; each instance needs a name of its own (--instance" in text
        said = [e for e in events.on("rlutf/events") if e["code"] == "instance_name_taken"]
        assert len(said) == 1, events.samples
        assert said[0]["level"] == "error" and said[0]["key"] == "rlutf/service/b"
        assert "scans since it started" in said[0]["message"]
        time.sleep(3.0)  # the older one runs on, every robot's scans answered
        assert older.process.poll() is None, older.log.read_text()[-3000:]
        assert live_members(near) == {"b"} and _claim(near, "b") == kept
        for robot in robots:
            after = [p for t, p in poses.of(robot) if t > t_gone + 0.5]
            assert len(after) >= 15, (robot, len(after))
            twice = [s for s, n in Counter(p["stamp_ns"] for p in after).items() if n > 1]
            assert not twice, (robot, twice)
        # The older one says so too, if the younger's claim reached it before the younger left
        # (on a busy host it may not: the younger sees the older's claim and goes first).
    finally:
        if driver is not None:
            driver.stop()
        for instance in (younger, older):
            if instance is not None:
                instance.stop()
        watched.undeclare()
        followed.undeclare()
        router.close()
        far.close()
        if bridge is not None:
            bridge.close()


def test_a_restart_waits_for_the_tokens_its_frozen_predecessor_left_and_starts(
    tmp_path: Path,
) -> None:
    """An instance b frozen (SIGSTOP: its session's tokens stay on the bus until Zenoh's lease,
    10 s, ends) is replaced by a new b, as a supervisor would after a failed health check: the
    new one waits for the old tokens to go, not taking them for another live instance for
    good, and then starts and answers as b."""
    router = Router.open(free_port(), tmp_path / "store")
    (tmp_path / "old").mkdir()
    (tmp_path / "new").mkdir()
    old = spawn_instance(router.endpoint, "b", tmp_path / "old")
    new: Instance | None = None
    try:
        assert wait_until(lambda: live_members(router.session) == {"b"}, 25.0)
        before = _claim(router.session, "b")
        assert before["session"] and before["claimed_ns"] > 0
        os.kill(old.process.pid, signal.SIGSTOP)
        frozen = time.monotonic()
        new = spawn_instance(router.endpoint, "b", tmp_path / "new")
        assert wait_until(
            lambda: _claim(router.session, "b").get("session") not in (None, before["session"]),
            40.0,
        ), new.log.read_text()[-3000:]
        waited = time.monotonic() - frozen
        assert new.process.poll() is None
        assert wait_until(lambda: "ready: instance b" in new.log.read_text(), 5.0)
        assert waited > 5.0  # it did wait for the lease (about 10 s after the freeze)
        assert live_members(router.session) == {"b"}
    finally:
        old.process.kill()  # frozen: SIGTERM would wait for it to be continued
        old.process.wait(10.0)
        if new is not None:
            new.stop()
        router.close()


def _connect(endpoint: str, host: subprocess.Popen[bytes], log: Path) -> zenoh.Session:
    """A client session of a host's router, once it listens."""
    end = time.monotonic() + 60.0
    while True:
        try:
            return zenoh.open(client_config(endpoint))
        except zenoh.ZError:
            assert host.poll() is None and time.monotonic() < end, log.read_text()[-3000:]
            time.sleep(0.2)


def test_two_hosts_of_one_name_meet_and_the_younger_host_stops(tmp_path: Path) -> None:
    """``rlutf serve --processes 2 --instance h`` twice, each its own router, apart until a
    router both connect to comes up: the younger host's processes lose h-p0 and h-p1 to the
    older's, and the younger host stops with exit 1, saying so; the older runs on."""
    ports = [free_port() for _ in range(3)]
    ends = [f"tcp/127.0.0.1:{p}" for p in ports]
    hosts: list[subprocess.Popen[bytes]] = []
    logs = [tmp_path / "older.log", tmp_path / "younger.log"]
    clients: list[zenoh.Session] = []
    bridge: zenoh.Session | None = None
    try:
        for k, log in enumerate(logs):
            folder = tmp_path / log.stem
            cmd = [sys.executable, "-m", "service", "serve", "--processes", "2", "--instance"]
            cmd += ["h", "--listen", ends[k], "--connect", ends[2], "--no-record"]
            cmd += ["--store", str(folder / "store"), "--state", str(folder / "state")]
            with log.open("wb") as out:
                hosts.append(subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT))
            clients.append(_connect(ends[k], hosts[k], log))
            assert wait_until(lambda c=clients[k]: live_members(c) == {"h-p0", "h-p1"}, 60.0), (
                log.read_text()[-3000:]
            )
        bridge = zenoh.open(session_config("router", listen=[ends[2]]))
        try:
            code = hosts[1].wait(30.0)
        except subprocess.TimeoutExpired:
            code = None
        text = logs[1].read_text()
        assert code == 1, text[-3000:]
        # it lost h-p0 and the host's own name h, whichever it learnt of first
        assert "rlutf serve: another instance named h" in text, text[-3000:]
        time.sleep(2.0)
        assert hosts[0].poll() is None, logs[0].read_text()[-3000:]
        assert live_members(clients[0]) == {"h-p0", "h-p1"}
        assert "claimed the name after this one" in logs[0].read_text()
    finally:
        for c in clients:
            c.close()
        for host in hosts:
            if host.poll() is None:
                host.terminate()
                try:
                    host.wait(30.0)
                except subprocess.TimeoutExpired:
                    host.kill()
                    host.wait(10.0)
        if bridge is not None:
            bridge.close()


def test_a_single_process_of_a_hosts_name_refuses_to_start_beside_it(tmp_path: Path) -> None:
    """``rlutf serve --processes 2 --instance h`` runs h-p0 and h-p1 and answers Health as h; a
    single-process ``rlutf serve --instance h`` joining its router exits 1, saying why, and
    takes no robot. It started before, a third member h beside h-p0 and h-p1, and a second
    answer to h's Health."""
    end = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "host.log"
    cmd = [sys.executable, "-m", "service", "serve", "--processes", "2", "--instance", "h"]
    cmd += ["--listen", end, "--no-record", "--store", str(tmp_path / "store")]
    cmd += ["--state", str(tmp_path / "state")]
    with log.open("wb") as out:
        host = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    client: zenoh.Session | None = None
    single: Instance | None = None
    try:
        client = session = _connect(end, host, log)
        ready = wait_until(lambda: live_members(session) == {"h-p0", "h-p1"}, 60.0)
        assert ready, log.read_text()[-3000:]
        (tmp_path / "single").mkdir()
        single = spawn_instance(end, "h", tmp_path / "single")
        code = _exit_code(single, 45.0)
        text = single.log.read_text()
        assert code == 1, text[-2000:]
        assert "an instance named h is live" in text, text[-2000:]
        assert "each instance needs a name of its own" in text, text[-2000:]
        assert host.poll() is None, log.read_text()[-3000:]
        assert live_members(client) == {"h-p0", "h-p1"}
        answers = [r.ok for r in client.get(Keys().health("h"), timeout=2.0) if r.ok]
        assert len(answers) == 1
    finally:
        if single is not None:
            single.stop()
        if client is not None:
            client.close()
        host.terminate()
        try:
            host.wait(30.0)
        except subprocess.TimeoutExpired:
            host.kill()
            host.wait(10.0)
