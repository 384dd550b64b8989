"""Pose puts held by a thread go out together, in order, when it releases them (real Zenoh
sessions on loopback: the service's router and a robot's client)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

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
