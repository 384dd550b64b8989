"""The front door alone on real Zenoh sessions: settings, namespaces, forced key naming."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from ros_client import TS, RosListener, initialpose_msg, key

from schemas import PoseEstimate, encode
from service.config import load_settings
from service.live.sessions import client_config, free_port, session_config
from service.ros2.frontdoor import Ros2FrontDoor

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


def test_settings_file_namespaces_maps_and_forced_naming(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("RLUTF_SETTINGS", raising=False)
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    path = tmp_path / "settings.toml"
    path.write_text(
        '[ros2]\nenabled = true\nmap_id = "m1"\n'
        '[ros2.robots."site/r7"]\nrobot_id = "r7"\nmap_id = "m7"\ndistro = "humble"\n',
        encoding="utf-8",
    )
    settings = load_settings(path)
    monkeypatch.delenv("RLUTF_SETTINGS", raising=False)
    assert settings.ros2.domain_id == 7
    assert settings.ros2.robot("/site/r7").robot_id == "r7"
    port = free_port()
    offers: list[tuple[str, str, bytes, object]] = []
    rejects: list[tuple[str | None, str, str]] = []
    with (
        zenoh.open(session_config("router", listen=[f"tcp/127.0.0.1:{port}"])) as router,
        zenoh.open(client_config(f"tcp/127.0.0.1:{port}")) as robot,
    ):
        door = Ros2FrontDoor(
            settings.ros2,
            lambda r, k, p, m, t: offers.append((r, k, p, m)),
            lambda r, k, why, t: rejects.append((r, k, why)),
            time.time_ns,
        )
        door.start(router)
        listener = RosListener()
        humble_key = key(7, "/site/r7/amcl_pose", POSE, humble=True)
        sub = robot.declare_subscriber(humble_key, listener)
        time.sleep(0.3)
        # The robot writes Jazzy keys; the settings force Humble naming for its outputs.
        msg = initialpose_msg(np.array([1.0, 2.0, 0.5]), 123)
        robot.put(
            key(7, "/site/r7/initialpose", POSE, humble=False), bytes(TS.serialize_cdr(msg, POSE))
        )
        robot.put(
            key(7, "/a/b/initialpose", POSE, humble=False), bytes(TS.serialize_cdr(msg, POSE))
        )
        robot.put(key(0, "/site/r7/initialpose", POSE, humble=False), b"other domain")
        end = time.monotonic() + 5
        while (not offers or not rejects) and time.monotonic() < end:
            time.sleep(0.02)
        assert [(r, k) for r, k, _, _ in offers] == [("r7", "initialpose")]
        assert offers[0][3].map_id == "m7"  # type: ignore[attr-defined]
        assert rejects and rejects[0][0] is None and "a/b" in rejects[0][2]
        assert door.robots() == {"r7": "/site/r7"}
        pose = PoseEstimate(
            stamp_ns=456,
            robot_id="r7",
            map_id="m7",
            x=1.0,
            y=2.0,
            theta=0.5,
            status="tracking",
            discrepancy=0.0,
            iterations=0,
        )
        door.on_pose("r7", encode(pose))
        door.on_pose("json-robot", encode(pose.model_copy(update={"robot_id": "json-robot"})))
        end = time.monotonic() + 5
        while not listener.on(humble_key) and time.monotonic() < end:
            time.sleep(0.02)
        ((raw, att),) = listener.on(humble_key)
        assert att is not None and len(att) == 33
        out = TS.deserialize_cdr(raw, POSE)
        assert (out.pose.pose.position.x, out.header.stamp.nanosec) == (1.0, 456)
        sub.undeclare()
        door.close()
