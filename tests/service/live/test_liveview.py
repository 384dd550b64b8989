"""The live view: a real service with ``foxglove_port``, read by a WebSocket client on loopback.

The client is the ``websockets`` library speaking the Foxglove protocol (``foxglove.sdk.v1``)
from its specification: JSON ``serverInfo`` and ``advertise`` text frames, a ``subscribe``
request, then binary message-data frames (opcode 1, subscription id u32, log time u64, payload).
"""

from __future__ import annotations

import json
import math
import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from service_harness import Bench, Collector, running_bench
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from service.live.foxview import FoxgloveView
from service.live.sessions import free_port
from service.logs.foxglove import embedded_dir

pytestmark = pytest.mark.integration

SUBPROTOCOL = "foxglove.sdk.v1"


class FoxgloveClient:
    """A minimal Foxglove WebSocket client: channels by topic, messages by topic."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}
        self.messages: dict[str, list[tuple[int, dict[str, Any]]]] = {}
        self.server_info: dict[str, Any] | None = None
        self._subs: dict[int, str] = {}

    def pump(self, seconds: float) -> None:
        """Read frames for ``seconds``."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    self.server_info = msg
                elif msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        self.channels[ch["topic"]] = ch
            elif frame[0] == 1:  # message data
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                topic = self._subs[sub]
                self.messages.setdefault(topic, []).append((log_time, json.loads(frame[13:])))

    def wait_channel(self, topic: str, timeout: float = 10.0) -> dict[str, Any]:
        end = time.monotonic() + timeout
        while topic not in self.channels and time.monotonic() < end:
            self.pump(0.1)
        return self.channels[topic]

    def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            ch = self.wait_channel(topic)
            sub_id = len(self._subs) + 1
            self._subs[sub_id] = topic
            subs.append({"id": sub_id, "channelId": ch["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def wait_messages(self, topic: str, count: int = 1, timeout: float = 10.0) -> list[Any]:
        end = time.monotonic() + timeout
        while len(self.messages.get(topic, [])) < count and time.monotonic() < end:
            self.pump(0.1)
        return [m for _, m in self.messages.get(topic, [])]


@contextmanager
def foxglove_client(url: str) -> Iterator[FoxgloveClient]:
    """A client connected to ``url`` with the Foxglove subprotocol."""
    with connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)]) as ws:
        yield FoxgloveClient(ws)


def _schema(name: str) -> dict[str, Any]:
    value: dict[str, Any] = json.loads((embedded_dir() / f"{name}.json").read_text())
    return value


def _drive(bench: Bench, robot: Any, steps: int) -> None:
    for _ in range(steps):
        robot.advance()
        time.sleep(0.03)


def test_an_operator_watches_a_robot_live(tmp_path: Path) -> None:
    with running_bench(tmp_path, foxglove_port=0) as bench:
        view = bench.service.live
        assert isinstance(view, FoxgloveView) and view.url is not None
        col = Collector()
        sub = bench.client.declare_subscriber("rlutf/robots/r1/pose", col)
        bench.put_map()
        time.sleep(0.3)
        r1 = bench.robot("r1", 1)
        r1.initial_pose("m1", (0.1, -0.05, 0.03))
        time.sleep(0.3)
        _drive(bench, r1, 10)
        assert col.wait_for(lambda: len(col.on("rlutf/robots/r1/pose")) >= 5)
        time.sleep(0.3)
        assert view.shown == 0  # no client follows anything yet: the map is shown on subscribing

        with foxglove_client(view.url) as client:
            client.pump(0.5)
            assert client.server_info is not None
            topics = [
                "/foxglove/maps/m1",
                "/foxglove/robots/r1/pose",
                "/foxglove/robots/r1/scan",
                "/foxglove/tf",
                "/foxglove/fleet",
            ]
            client.subscribe(*topics)
            for topic in topics:
                assert client.wait_messages(topic), topic  # the newest, on subscribing
            _drive(bench, r1, 10)
            poses = client.wait_messages("/foxglove/robots/r1/pose", 3)
            assert len(poses) >= 3
            # the pose shown is one the service published, in the map frame
            published = col.on("rlutf/robots/r1/pose")
            last = poses[-1]
            jsonschema.validate(last, _schema("foxglove.PoseInFrame"))
            assert last["frame_id"] == "map"
            match = [
                p
                for p in published
                if math.isclose(p["x"], last["pose"]["position"]["x"])
                and math.isclose(p["y"], last["pose"]["position"]["y"])
            ]
            assert match, "a pose the service never published"
            tf = client.wait_messages("/foxglove/tf")[-1]
            jsonschema.validate(tf, _schema("foxglove.FrameTransform"))
            assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("map", "r1/base_link")
            scan = client.wait_messages("/foxglove/robots/r1/scan")[-1]
            jsonschema.validate(scan, _schema("foxglove.LaserScan"))
            assert scan["frame_id"] == "r1/base_link" and len(scan["ranges"]) == 180
            fleet = client.wait_messages("/foxglove/fleet")[-1]
            jsonschema.validate(fleet, _schema("foxglove.SceneUpdate"))
            entity = fleet["entities"][0]
            assert entity["id"] == "robot/r1"
            assert entity["texts"][0]["text"].startswith("r1 ")
            status = {m["key"]: m["value"] for m in entity["metadata"]}["status"]
            assert status in ("tracking", "corrected")
            the_map = client.wait_messages("/foxglove/maps/m1")[-1]
            jsonschema.validate(the_map, _schema("foxglove.SceneUpdate"))
            assert the_map["entities"][0]["lines"]
        sub.undeclare()


def test_views_refresh_at_most_at_the_rate(tmp_path: Path) -> None:
    """A robot scanning at ~30 Hz is shown at most ``foxglove_rate_hz`` times a second."""
    with running_bench(tmp_path, foxglove_port=0, foxglove_rate_hz=5.0) as bench:
        view = bench.service.live
        assert view.url is not None
        bench.put_map()
        time.sleep(0.3)
        r1 = bench.robot("r1", 1)
        r1.initial_pose("m1")
        with foxglove_client(view.url) as client:
            client.subscribe("/foxglove/robots/r1/scan")
            t0 = time.monotonic()
            _drive(bench, r1, 60)  # ~2 s at ~30 scans a second
            client.pump(0.5)
            elapsed = time.monotonic() - t0
            shown = len(client.messages.get("/foxglove/robots/r1/scan", []))
            assert 1 <= shown <= 5.0 * elapsed + 2


def test_a_port_in_use_fails_the_start(tmp_path: Path) -> None:
    from service.live.foxview import LiveViewError

    with running_bench(tmp_path / "a", foxglove_port=0) as bench:
        url = bench.service.live.url
        assert url is not None
        port = int(url.rsplit(":", 1)[1])
        with (
            pytest.raises(LiveViewError, match=f"127.0.0.1:{port}"),
            running_bench(tmp_path / "b", foxglove_port=port),
        ):
            pass


def test_rlutf_serve_foxglove_port_prints_where_to_connect(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("rlutf")
    cmd = [str(exe), "serve", "--foxglove-port", "0", "--listen", f"tcp/127.0.0.1:{free_port()}"]
    cmd += ["--store", str(tmp_path / "store"), "--no-record", "--workers", "0"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("RLUTF_")}
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env
    )
    try:
        assert proc.stderr is not None
        url = None
        end = time.monotonic() + 180
        while url is None and time.monotonic() < end:
            line = proc.stderr.readline()
            if not line:
                break
            if "live view on ws://" in line:
                url = line.split("live view on ", 1)[1].split()[0]
        assert url is not None and not url.endswith(":0")
        with foxglove_client(url) as client:
            client.pump(1.0)
            assert client.server_info is not None
            assert {"/foxglove/tf", "/foxglove/fleet"} <= set(client.channels)
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0


def test_map_health_is_drawn_over_the_map_live(tmp_path: Path) -> None:
    """A MapHealth the service puts (and records) is drawn on /foxglove/maphealth/{map_id}:
    an added rack outlined, a removed wall as a line, each labelled."""
    from schemas import MapHealth, encode

    health = MapHealth.model_validate(
        {
            "map_id": "m1",
            "version": 1,
            "stamp_ns": 1_732_300_000_000_000_000,
            "since_ns": 1_732_290_000_000_000_000,
            "scans": 1000,
            "robots": 3,
            "changes": [
                {
                    "kind": "added",
                    "geometry": {
                        "type": "Polygon",
                        "coordinates": [
                            [[4.1, 2.0], [5.3, 2.0], [5.3, 2.8], [4.1, 2.8], [4.1, 2.0]]
                        ],
                    },
                    "evidence": 512,
                    "robots": 3,
                    "first_ns": 1_732_291_000_000_000_000,
                    "last_ns": 1_732_299_900_000_000_000,
                    "confidence": 0.97,
                },
                {
                    "kind": "removed",
                    "geometry": {"type": "LineString", "coordinates": [[10.0, 0.0], [12.0, 0.0]]},
                    "evidence": 81,
                    "robots": 2,
                    "first_ns": 1_732_292_000_000_000_000,
                    "last_ns": 1_732_299_000_000_000_000,
                    "confidence": 0.88,
                },
            ],
        }
    )
    with running_bench(tmp_path, foxglove_port=0) as bench:
        view = bench.service.live
        assert view.url is not None
        with foxglove_client(view.url) as client:
            feed = bench.service.healthfeed
            t = time.time_ns()
            feed.record("rlutf/maphealth/m1", "rlutf.MapHealth", encode(health), t, t)
            client.subscribe("/foxglove/maphealth/m1")
            feed.record("rlutf/maphealth/m1", "rlutf.MapHealth", encode(health), t, t)
            (update, *_) = client.wait_messages("/foxglove/maphealth/m1")
    jsonschema.validate(update, _schema("foxglove.SceneUpdate"))
    (entity,) = update["entities"]
    assert entity["id"] == "maphealth/m1"
    outlines = [[(p["x"], p["y"]) for p in line["points"]] for line in entity["lines"]]
    assert outlines[0][:2] == [(4.1, 2.0), (5.3, 2.0)] and len(outlines[0]) == 5
    assert outlines[1] == [(10.0, 0.0), (12.0, 0.0)]
    assert entity["lines"][0]["color"] != entity["lines"][1]["color"]
    assert [t["text"] for t in entity["texts"]] == [
        "added 97 % (3 robots)",
        "removed 88 % (2 robots)",
    ]
