"""Maps of real size (issue 20) and of large extent (issue 19), on a real service over Zenoh.

A warehouse of thousands of traced racks (megabytes of JSON, over the robots' message limit)
is put with the map tool, localized on live in a worker process, recorded, and replayed to the
same poses. A 144-byte 2 km square is refused with an Event before any work; a 40,000-vertex
room is built in the worker of the robot that needs it while the other robots keep their poses.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from service_harness import wait_until

from bench.bigmap import aisle_y, warehouse
from bench.mapload import PeakRss, SteadyFleet, rss_mb, scan_payload, square_map, wavy_room
from rlutf.map import Map as World
from rlutf.sim import LidarModel, simulate_scan
from schemas import InitialPose, LaserScan, Map, Odometry, encode
from service.config import Settings
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.mcaplog import McapRecorder
from service.logs.replay import replay
from service.maps.client import put_map

pytestmark = pytest.mark.integration
JSON = zenoh.Encoding.APPLICATION_JSON
RACKS = (50, 40)  # 2,000 racks


def _service(folder: Path, workers: int, record: bool = False) -> LocalizationService:
    port = free_port()
    settings = Settings(
        listen=[f"tcp/127.0.0.1:{port}"],
        store_dir=folder / "store",
        record_dir=folder / "logs",
        no_record=not record,
        workers=workers,
        instance=f"big-{port}",
        event_interval_s=0.0,
    )
    recorder = McapRecorder(settings.record_dir, instance=settings.instance) if record else None
    return LocalizationService(settings, recorder=recorder).start()


def _endpoint(service: LocalizationService) -> str:
    return service.settings.listen[0]


def _events(session: zenoh.Session) -> tuple[list[dict[str, Any]], Any]:
    seen: list[dict[str, Any]] = []
    sub = session.declare_subscriber(
        "rlutf/events", lambda s: seen.append(json.loads(s.payload.to_bytes()))
    )
    return seen, sub


def _drive(
    session: zenoh.Session, robot: str, map_id: str, world: World, truth: np.ndarray
) -> tuple[list[dict[str, Any]], int]:
    """InitialPose at the first pose, scans there until the first pose comes (the worker builds
    the map meanwhile), then odometry and a scan per pose of ``truth`` at 10 Hz.

    Returns:
        Every pose received, and the stamp of the first scan of the drive.
    """
    poses: list[dict[str, Any]] = []
    sub = session.declare_subscriber(
        f"rlutf/robots/{robot}/pose", lambda s: poses.append(json.loads(s.payload.to_bytes()))
    )
    rng = np.random.default_rng(5)
    t0 = time.time_ns()
    step = 0

    def send(pose: np.ndarray) -> int:
        nonlocal step
        x, y, th = (float(v) for v in pose)
        stamp = t0 + step * 100_000_000
        step += 1
        session.put(
            f"rlutf/robots/{robot}/odom",
            encode(Odometry(stamp_ns=stamp, x=x, y=y, theta=th)),
            encoding=JSON,
        )
        s = simulate_scan(world, pose, LidarModel(beams=360), rng)
        session.put(f"rlutf/robots/{robot}/scan", scan_payload(s, stamp), encoding=JSON)
        time.sleep(0.1)
        return stamp

    x, y, th = (float(v) for v in truth[0])
    session.put(
        f"rlutf/robots/{robot}/odom",
        encode(Odometry(stamp_ns=t0 - 1, x=x, y=y, theta=th)),
        encoding=JSON,
    )
    init = InitialPose(stamp_ns=t0 - 1, map_id=map_id, x=x, y=y, theta=th)
    session.put(f"rlutf/robots/{robot}/initialpose", encode(init), encoding=JSON)
    end = time.monotonic() + 120.0
    while not poses and time.monotonic() < end:
        send(truth[0])
    first = t0 + step * 100_000_000
    for pose in truth[1:]:
        last = send(pose)
    wait_until(lambda: any(p["stamp_ns"] == last for p in poses), 30.0)
    sub.undeclare()
    return poses, first


def test_a_warehouse_of_thousands_of_racks_live_and_in_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    geometry = warehouse(*RACKS)
    payload = encode(Map(map_id="warehouse", version=1, geometry=geometry))
    assert len(payload) > 3 * Settings().max_payload_bytes  # several MB: over a robot's limit
    assert len(geometry["coordinates"]) - 1 == RACKS[0] * RACKS[1]
    world = World.from_geojson(geometry)
    service = _service(tmp_path, workers=1, record=True)
    try:
        with zenoh.open(client_config(_endpoint(service))) as client:
            events, sub = _events(client)
            path = tmp_path / "warehouse.json"
            path.write_bytes(payload)
            assert put_map(client, "rlutf", path, None, "next", timeout=120.0) == 0
            assert "stored" in capsys.readouterr().out
            assert (tmp_path / "store" / "warehouse.json").read_bytes() == payload
            assert wait_until(lambda: service.maps.get("warehouse") is not None, 30.0)
            assert not [e for e in events if e["code"] in ("invalid_map", "invalid_message")]
            steps = 40
            truth = np.column_stack(
                [10.0 + 0.08 * np.arange(steps), np.full(steps, aisle_y(RACKS[1])), np.zeros(steps)]
            )
            poses, first = _drive(client, "picker", "warehouse", world, truth)
            sub.undeclare()
    finally:
        service.close()
    driving = [p for p in poses if p["stamp_ns"] >= first]
    # 10 Hz once the map is built; on a loaded machine a few scans are superseded (counted
    # and recorded as dropped, which the replay below checks too).
    assert len(driving) >= steps * 3 // 4
    last = poses[-1]
    assert last["map_id"] == "warehouse" and last["status"] != "lost"
    assert math.hypot(last["x"] - truth[-1, 0], last["y"] - truth[-1, 1]) < 0.05
    # Recorded, and replay (with default settings) takes the same map to the same poses.
    logs = sorted((tmp_path / "logs").glob("*.mcap"))
    result = replay(logs)
    assert result.maps["warehouse"] == payload
    assert result.rejected == 0
    recorded = [p.payload for p in result.recorded["picker"]]
    assert len(recorded) == len(poses)
    assert [p.payload for p in result.recomputed["picker"]] == recorded


def _steady(client: zenoh.Session) -> SteadyFleet:
    fleet = SteadyFleet(client, robots=3, seconds=30.0)
    fleet.start()
    assert fleet.wait_steady(), "the steady robots never got steady poses"
    return fleet


def test_a_2km_square_is_refused_before_any_work_and_stalls_no_one(tmp_path: Path) -> None:
    service = _service(tmp_path, workers=2)
    try:
        with zenoh.open(client_config(_endpoint(service))) as client, PeakRss() as rss:
            fleet = _steady(client)
            baseline = rss_mb()
            events, sub = _events(client)
            t0 = time.monotonic()
            client.put("rlutf/maps/square", square_map("square", 2000.0), encoding=JSON)
            assert wait_until(lambda: any(e["code"] == "invalid_map" for e in events), 5.0)
            refused_s = time.monotonic() - t0
            time.sleep(3.0)
            window = fleet.window(t0, t0 + 3.0)
            fleet.stop()
            sub.undeclare()
        (event,) = [e for e in events if e["code"] == "invalid_map"]
        assert "max_map_area" in event["message"] and "2000 m x 2000 m" in event["message"]
        assert event["key"] == "rlutf/maps/square"
        assert service.maps.get("square") is None
        assert not (tmp_path / "store" / "square.json").exists()
    finally:
        service.close()
    assert refused_s < 1.0
    assert window["max_gap_s"] < 1.0, window
    assert window["answered"] >= 0.9, window
    # This process is the service's main process and the test's; its workers and map checker
    # are its children. The bench (bench.bigmap) measures a service alone.
    assert rss.peak - baseline < 300, f"{baseline:.0f} MB, then up to {rss.peak:.0f} MB"


def test_a_40000_vertex_map_is_built_off_the_other_robots_path(tmp_path: Path) -> None:
    room = wavy_room(40_000)
    world = World.from_geojson(room)
    service = _service(tmp_path, workers=2)
    try:
        with zenoh.open(client_config(_endpoint(service))) as client, PeakRss() as rss:
            fleet = _steady(client)
            baseline = rss_mb()
            events, sub = _events(client)
            t0 = time.monotonic()
            client.put(
                "rlutf/maps/wavy",
                encode(Map(map_id="wavy", version=1, geometry=room)),
                encoding=JSON,
            )
            assert wait_until(lambda: service.maps.get("wavy") is not None, 10.0)
            truth = np.column_stack([0.05 * np.arange(20), np.zeros(20), np.zeros(20)])
            poses, first = _drive(client, "rover", "wavy", world, truth)
            window = fleet.window(t0, time.monotonic())
            fleet.stop()
            sub.undeclare()
        assert not [e for e in events if e["code"] == "invalid_map"]
    finally:
        service.close()
    assert len([p for p in poses if p["stamp_ns"] >= first]) >= 15
    assert poses[-1]["status"] != "lost"
    assert window["max_gap_s"] < 1.0, window
    assert window["answered"] >= 0.9, window
    # This process is the service's main process and the test's; its workers and map checker
    # are its children. The bench (bench.bigmap) measures a service alone.
    assert rss.peak - baseline < 300, f"{baseline:.0f} MB, then up to {rss.peak:.0f} MB"


def test_replay_applies_the_same_limits(tmp_path: Path) -> None:
    """An audit reproduces which maps the service refused: the limits are in the log's config."""
    from service.logs.mcapfile import LogWriter, Record

    assert Settings().max_map_bytes >= 64 * 1024 * 1024
    assert Settings().max_payload_bytes <= 1_000_000
    big = encode(Map(map_id="hall", version=1, geometry=warehouse(4, 4)))
    records = [
        Record("rlutf/maps/square", "rlutf.Map", square_map("square", 2000.0), 1, 1),
        Record("rlutf/maps/hall", "rlutf.Map", big, 2, 2),
    ]
    for name, config, rejected in [
        ("defaults", None, 1),  # the square only
        ("tight", {"max_map_vertices": 100}, 2),  # the hall too
        ("raised", {"max_map_area": 5e6}, 0),
    ]:
        path = tmp_path / f"{name}.mcap"
        with open(path, "wb") as stream:
            writer = LogWriter(stream)
            if config is not None:
                writer.write_config(config)
            writer.write_all(records)
            writer.finish()
        result = replay([path])
        assert result.rejected == rejected, name


def _send_carmen(client: zenoh.Session, scan: Any, stamp: int) -> None:
    """A CARMEN scan and its (corrected) pose as odometry, laser at the base."""
    x, y, th = (float(v) for v in scan.pose)
    odom = Odometry(stamp_ns=stamp, x=x, y=y, theta=th)
    client.put("rlutf/robots/intel/odom", encode(odom), encoding=JSON)
    msg = LaserScan(
        stamp_ns=stamp,
        angle_min=float(scan.angles[0]),
        angle_increment=float(scan.angles[1] - scan.angles[0]),
        range_min=0.05,
        range_max=float(scan.max_range) - 1e-3,  # at max: no return
        ranges=[float(r) for r in scan.ranges],
    )
    client.put("rlutf/robots/intel/scan", encode(msg), encoding=JSON)


def test_a_map_built_from_a_real_log_live_and_in_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`rlutf map build --put` on the CARMEN intel log: stored, loaded, localized on with the
    log's own scans, recorded and replayed to the same poses, all with default settings."""
    from bench.scenarios import DATA
    from service.cli.main import main
    from service.maps.mapimport import read_carmen

    log = DATA / "carmen" / "intel-corrected.log.gz"
    service = _service(tmp_path, workers=1, record=True)
    try:
        with zenoh.open(client_config(_endpoint(service))) as client:
            out = tmp_path / "intel.json"
            argv = ["map", "build", str(log), "--id", "intel", "--out", str(out), "--put"]
            assert main([*argv, "--connect", _endpoint(service)]) == 0
            assert "stored" in capsys.readouterr().out
            assert wait_until(lambda: service.maps.get("intel") is not None, 60.0)
            payload = (tmp_path / "store" / "intel.json").read_bytes()
            carmen = read_carmen(log)
            poses: list[dict[str, Any]] = []
            sub = client.declare_subscriber(
                "rlutf/robots/intel/pose", lambda s: poses.append(json.loads(s.payload.to_bytes()))
            )
            t0 = time.time_ns()
            first = carmen.scans[0].pose
            init = InitialPose(stamp_ns=t0, map_id="intel", x=first[0], y=first[1], theta=first[2])
            odom0 = Odometry(stamp_ns=t0, x=first[0], y=first[1], theta=first[2])
            client.put("rlutf/robots/intel/odom", encode(odom0), encoding=JSON)
            client.put("rlutf/robots/intel/initialpose", encode(init), encoding=JSON)
            steps = 30
            # The first scan until the first pose (the worker builds the map meanwhile; scans
            # sent then would be superseded), then one scan every 0.1 s.
            stamp = t0
            end = time.monotonic() + 120.0
            while not poses and time.monotonic() < end:
                stamp += 100_000_000
                _send_carmen(client, carmen.scans[1], stamp)
                time.sleep(0.2)
            for scan in carmen.scans[2 : steps + 1]:
                stamp += 100_000_000
                _send_carmen(client, scan, stamp)
                time.sleep(0.1)
            last = stamp
            wait_until(lambda: any(p["stamp_ns"] == last for p in poses), 60.0)
            sub.undeclare()
    finally:
        service.close()
    assert len(poses) >= steps // 2
    truth = carmen.scans[steps].pose
    assert poses[-1]["stamp_ns"] == last
    assert math.hypot(poses[-1]["x"] - truth[0], poses[-1]["y"] - truth[1]) < 0.1
    result = replay(sorted((tmp_path / "logs").glob("*.mcap")))
    assert result.maps["intel"] == payload and result.rejected == 0
    recorded = [p.payload for p in result.recorded["intel"]]
    assert len(recorded) == len(poses)
    assert [p.payload for p in result.recomputed["intel"]] == recorded
