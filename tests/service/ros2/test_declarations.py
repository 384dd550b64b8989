"""A ROS robot's tokens and publishers are declared on the front door's own thread, never in the
Zenoh callback its input comes in: a declaration that waits on the bus holds up no input and no
other robot's pose (real Zenoh sessions on loopback)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import zenoh
from ros_client import TS, RosListener, initialpose_msg, key
from service_harness import wait_until

from schemas import PoseEstimate, encode
from service.config import Ros2Settings
from service.live.sessions import client_config, free_port, session_config
from service.ros2 import roster
from service.ros2.frontdoor import Ros2FrontDoor

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


@dataclass
class Door:
    door: Ros2FrontDoor
    robot: zenoh.Session
    offers: list[tuple[str, str]] = field(default_factory=list)

    def initial_pose(self, namespace: str, humble: bool = False) -> None:
        msg = initialpose_msg(np.array([1.0, 2.0, 0.5]), 123)
        k = key(0, f"{namespace}/initialpose", POSE, humble)
        self.robot.put(k, bytes(TS.serialize_cdr(msg, POSE)))

    def tokens(self, part: str) -> list[str]:
        replies = self.robot.liveliness().get("@ros2_lv/**", timeout=2.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None and part in str(r.ok)]


@contextmanager
def front_door() -> Iterator[Door]:
    port = free_port()
    with (
        zenoh.open(session_config("router", listen=[f"tcp/127.0.0.1:{port}"])) as router,
        zenoh.open(client_config(f"tcp/127.0.0.1:{port}")) as robot,
    ):
        offers: list[tuple[str, str]] = []
        door = Ros2FrontDoor(
            Ros2Settings(enabled=True, map_id="m1"),
            lambda r, k, p, m, t: offers.append((r, k)),
            lambda r, k, why, t: None,
            time.time_ns,
        )
        door.start(router)
        try:
            yield Door(door, robot, offers)
        finally:
            door.close()


def _pose(robot: str, stamp_ns: int) -> bytes:
    return encode(
        PoseEstimate(
            stamp_ns=stamp_ns,
            robot_id=robot,
            map_id="m1",
            x=1.0,
            y=2.0,
            theta=0.5,
            status="tracking",
            discrepancy=0.0,
            iterations=0,
        )
    )


def _stamps(listener: RosListener, k: str) -> list[int]:
    return [TS.deserialize_cdr(raw, POSE).header.stamp.nanosec for raw, _ in listener.on(k)]


def test_a_declaration_stalled_on_the_bus_holds_up_no_input_and_no_pose(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # robot1's publishers wait as a declaration does while a link's queue is full (zenoh's
    # congestion control block: up to 5 s); robot2, declared before, is served meanwhile.
    release, begun = threading.Event(), threading.Event()
    threads: set[str] = set()
    declare = roster.declare_publisher

    def stalled(session: zenoh.Session, k: str, qos: Any) -> Any:
        threads.add(threading.current_thread().name)
        if "/robot1/" in k:
            begun.set()
            release.wait(20.0)
        return declare(session, k, qos)

    monkeypatch.setattr(roster, "declare_publisher", stalled)
    listener = RosListener()
    pose1, pose2 = (key(0, f"/robot{i}/amcl_pose", POSE, False) for i in (1, 2))
    with front_door() as d:
        subs = [d.robot.declare_subscriber(k, listener) for k in (pose1, pose2)]
        try:
            time.sleep(0.3)
            d.initial_pose("/robot2")
            assert wait_until(lambda: d.tokens("robot2%amcl_pose"))
            d.initial_pose("/robot1")
            assert begun.wait(5.0)  # robot1's declaration has begun, and waits
            d.initial_pose("/robot2")
            # Every input is handed on, robot1's too, though its declaration has not ended.
            assert wait_until(lambda: len(d.offers) == 3), d.offers
            assert sorted(d.offers) == [("robot1", "initialpose")] + [("robot2", "initialpose")] * 2
            # Poses: robot2's goes out; robot1's wait (the output thread does not), the latest.
            started = time.monotonic()
            d.door.on_pose("robot1", _pose("robot1", 1))
            d.door.on_pose("robot1", _pose("robot1", 2))
            d.door.on_pose("robot2", _pose("robot2", 3))
            assert time.monotonic() - started < 1.0
            assert wait_until(lambda: _stamps(listener, pose2) == [3])
            assert _stamps(listener, pose1) == []
            assert not d.tokens("robot1%tf/")  # declared after amcl_pose's publisher
        finally:
            release.set()
        # Declared: robot1's tokens show, and its latest pose goes out (the first of its key).
        assert wait_until(lambda: d.tokens("robot1%tf/"))
        assert wait_until(lambda: _stamps(listener, pose1) == [2])
        ((_, att),) = listener.on(pose1)
        assert att is not None and int.from_bytes(att[:8], "little") == 1
        d.door.on_pose("robot1", _pose("robot1", 4))
        assert wait_until(lambda: _stamps(listener, pose1) == [2, 4])
        for s in subs:
            s.undeclare()
    assert threads == {"rlutf-ros2-declare"}


def test_a_robot_that_changes_key_naming_is_declared_anew() -> None:
    listener = RosListener()
    humble, jazzy = (key(0, "/robot1/amcl_pose", POSE, h) for h in (True, False))
    with front_door() as d:
        subs = [d.robot.declare_subscriber(k, listener) for k in (humble, jazzy)]
        time.sleep(0.3)
        d.initial_pose("/robot1", humble=True)
        assert wait_until(lambda: d.tokens("TypeHashNotSupported"))
        d.initial_pose("/robot1", humble=False)  # the robot now runs Jazzy
        assert wait_until(lambda: d.tokens("RIHS01") and not d.tokens("TypeHashNotSupported"))
        d.door.on_pose("robot1", _pose("robot1", 5))
        assert wait_until(lambda: _stamps(listener, jazzy) == [5])
        assert _stamps(listener, humble) == []
        for s in subs:
            s.undeclare()
