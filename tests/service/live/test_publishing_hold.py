"""Pose puts held by a thread go out together, in order, when it releases them, and the
recorder's own Events go out and into the service's log (real Zenoh sessions on loopback: the
service's router and a robot's client)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from schemas import Event, EventCode, decode
from service.keys import Keys
from service.live.outbox import Outbox
from service.live.publishing import Announcer
from service.live.sessions import client_config, free_port, session_config
from service.logs.recording import NullRecorder


@pytest.fixture
def bus() -> Iterator[tuple[Announcer, zenoh.Session, zenoh.Session]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(session_config("router", listen=[endpoint]))
    client = zenoh.open(client_config(endpoint))
    announcer = Announcer(Keys(), NullRecorder(), time.time_ns, Outbox())
    announcer.attach(router)
    try:
        yield announcer, router, client
    finally:
        announcer.close()
        client.close()
        router.close()


def _received(sub: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]], wait: float) -> list[bytes]:
    got: list[bytes] = []
    end = time.monotonic() + wait
    while time.monotonic() < end:
        sample = sub.try_recv()
        if sample is None:
            time.sleep(0.01)
        else:
            got.append(sample.payload.to_bytes())
    return got


def test_held_poses_go_out_on_release_in_order_and_other_threads_are_not_held(
    bus: tuple[Announcer, zenoh.Session, zenoh.Session],
) -> None:
    announcer, _, client = bus
    keys = Keys()
    sub = client.declare_subscriber(keys.robot("*", "pose"), zenoh.handlers.FifoChannel(100))
    end = time.monotonic() + 10.0
    while not _received(sub, 0.05):  # the route is up once a lone put arrives
        assert time.monotonic() < end, "the client never received a pose"
        announcer.publish(keys.robot("r0", "pose"), b"warm", pose=True)
    _received(sub, 0.2)

    announcer.hold()
    for k, robot in enumerate(["r1", "r2", "r1"]):
        announcer.publish(keys.robot(robot, "pose"), f"pose {k}".encode(), pose=True)
    other = threading.Thread(
        target=announcer.publish,
        args=(keys.robot("r3", "pose"), b"not held"),
        kwargs={"pose": True},
    )
    other.start()
    other.join()
    assert _received(sub, 0.3) == [b"not held"]  # only the other thread's put went out
    assert announcer.release(older_than=60.0) == 0  # the oldest is younger than that
    assert _received(sub, 0.2) == []
    assert announcer.release() == 3
    assert _received(sub, 0.5) == [b"pose 0", b"pose 1", b"pose 2"]
    assert announcer.release() == 0  # nothing is put twice
    announcer.publish(keys.robot("r1", "pose"), b"still held", pose=True)  # the thread holds on
    time.sleep(0.02)
    assert announcer.release(older_than=0.01) == 1
    assert _received(sub, 0.5) == [b"still held"]


def test_the_recorders_own_events_reach_the_services_log_and_the_bus(
    bus: tuple[Announcer, zenoh.Session, zenoh.Session],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A full disk stopped the audit log with an Event on the bus only: nothing in the
    service's own output (its terminal, its journal). Now once in each."""
    from service.logs import mcaplog

    announcer, router, client = bus
    announcer.outbox.start(router)  # Events go out through the outbox, as in the service
    monkeypatch.setattr(mcaplog, "RETRY_S", 60.0)
    folder = tmp_path / "logs"
    rec = mcaplog.McapRecorder(folder, instance="t1", max_seconds=0.2, flush_interval_s=0.05)
    rec.on_event = announcer.recorder_event  # as the service wires it
    sub = client.declare_subscriber(Keys().events, zenoh.handlers.FifoChannel(100))
    time.sleep(0.5)
    caplog.set_level(logging.INFO)
    folder.rename(tmp_path / "gone")  # the write error a full disk gives
    for n in range(1, 60):
        rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', n, n)
        time.sleep(0.01)
        if rec.errors:
            break
    got = [decode(Event, p) for p in _received(sub, 1.0)]
    rec.close()
    announcer.outbox.close()
    assert [e.code for e in got] == [EventCode.RECORDING_FAILED], got
    lines = [r for r in caplog.records if "recording_failed" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING, caplog.text
    assert str(folder) in lines[0].getMessage()
