"""A live run with Relocalize messages, recorded to MCAP, replays to the same poses byte for byte.

Relocalize messages are inputs (WIRE.md v1.1): recorded on ``{prefix}/robots/{robot}/relocalize``
with schema ``rlutf.Relocalize``, and fed to the engine by replay in ``log_time`` order.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from mcaplog_fixtures import STEP_NS, T0, read_all, simulated_inputs
from service_harness import wait_until

from schemas import Region, Relocalize, encode
from service.config import Settings
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.mcapfile import Record
from service.logs.mcaplog import McapRecorder
from service.logs.replay import replay

pytestmark = pytest.mark.integration

STEPS = 24
ROBOTS = ("r1", "r2")


def _requests() -> dict[int, list[Record]]:
    """Operator requests, by the step before whose inputs they are put."""

    def rec(robot: str, msg: Relocalize | bytes, stamp: int) -> Record:
        payload = msg if isinstance(msg, bytes) else encode(msg)
        return Record(f"rlutf/robots/{robot}/relocalize", "rlutf.Relocalize", payload, 0, stamp)

    s8, s12, s16 = (T0 + k * STEP_NS for k in (8, 12, 16))
    return {
        8: [rec("r2", Relocalize(stamp_ns=s8, map_id="m1"), s8)],
        12: [
            rec("r1", Relocalize(stamp_ns=s12, map_id="nowhere"), s12),
            rec("r1", b'{"stamp_ns": 1, "map_id": "m1", "region": {"x": 0, "radius": 0}}', s12),
        ],
        16: [
            rec(
                "r1",
                Relocalize(stamp_ns=s16, map_id="m1", region=Region(x=5.0, y=5.0, radius=40.0)),
                s16,
            )
        ],
    }


def _record(folder: Path, workers: int) -> Path:
    port = free_port()
    settings = Settings(
        listen=[f"tcp/127.0.0.1:{port}"],
        store_dir=folder / "store",
        record_dir=folder / "logs",
        workers=workers,
        instance=f"reloc-{workers}",
        event_interval_s=0.0,
    )
    recorder = McapRecorder(settings.record_dir, instance=settings.instance)
    service = LocalizationService(settings, recorder=recorder).start()
    client = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    try:
        records = simulated_inputs(ROBOTS, steps=STEPS, seed=31)
        client.put(records[0].topic, records[0].payload)  # the map, into the embedded store
        assert wait_until(lambda: "m1" in service.maps_held(), 10.0)
        requests = _requests()

        def answered(stamp: int) -> bool:
            return all(
                f'"stamp_ns":{stamp}'.encode() in service._poses.get(rb, b"") for rb in ROBOTS
            )

        previous = -1
        for r in records[1:]:
            step = (r.publish_time_ns - T0) // STEP_NS
            if step != previous:
                if previous == 1:  # worker processes take a while to start on a busy machine
                    assert wait_until(lambda: answered(T0 + STEP_NS), 30.0), "no first poses"
                previous = step
                time.sleep(0.08)
                for q in requests.get(step, []):
                    client.put(q.topic, q.payload)
            client.put(r.topic, r.payload)
        assert wait_until(lambda: answered(T0 + STEPS * STEP_NS), 20.0), (
            "no poses for the last scans"
        )
    finally:
        client.close()
        service.close()
    (path,) = recorder.files
    return path


@pytest.fixture(scope="module", params=[0, 1], ids=["threads", "process"])
def live(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Path]:
    yield _record(tmp_path_factory.mktemp(f"reloc{request.param}"), request.param)


def test_relocalize_messages_are_recorded_as_inputs(live: Path) -> None:
    recorded = read_all(live, ["rlutf.Relocalize"])
    # The bad payload was rejected at the callback: not an input, so not in the log.
    assert [(r.topic, json.loads(r.payload)["map_id"]) for r in recorded] == [
        ("rlutf/robots/r2/relocalize", "m1"),
        ("rlutf/robots/r1/relocalize", "nowhere"),
        ("rlutf/robots/r1/relocalize", "m1"),
    ]
    events = [json.loads(r.payload) for r in read_all(live, ["rlutf.Event"])]
    codes = [(e["key"], e["code"]) for e in events]
    assert ("rlutf/robots/r1/relocalize", "invalid_message") in codes
    assert ("rlutf/maps/nowhere", "map_not_found") in codes
    for robot in ("r1", "r2"):
        mine = [c for k, c in codes if k.startswith(f"rlutf/robots/{robot}/") and "reloc" in c]
        assert mine == ["relocalizing", "relocalized"], (robot, codes)


def test_replay_reproduces_the_poses_byte_for_byte(live: Path, tmp_path: Path) -> None:
    first = replay([live], tmp_path / "one.mcap")
    for robot in ROBOTS:
        recorded = [p.payload for p in first.recorded[robot]]
        assert len(recorded) >= STEPS // 2
        stamps = [p.stamp_ns for p in first.recorded[robot]]
        assert [p.stamp_ns for p in first.recomputed[robot]] == stamps
        assert [p.payload for p in first.recomputed[robot]] == recorded
    # The relocalizations are in the poses: a global search, then tracking near the truth.
    r2 = [json.loads(p.payload) for p in first.recomputed["r2"]]
    assert all(p["map_id"] == "m1" for p in r2)
    assert r2[-1]["status"] != "lost"
    # The output holds the Relocalize inputs and replays to the same poses again.
    assert len(read_all(tmp_path / "one.mcap", ["rlutf.Relocalize"])) == 3
    again = replay([tmp_path / "one.mcap"])
    assert again.recomputed == first.recomputed
