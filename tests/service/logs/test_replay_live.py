"""Record a live run of the real service over Zenoh, then replay and audit it.

The service runs in this process (worker threads, or two worker processes) with the MCAP
recorder; a Zenoh client session publishes a simulated two-robot run, with a burst that makes
the service drop scans. Replaying the log must give the live poses byte for byte.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from mcaplog_fixtures import read_all, simulated_inputs, write_log
from service_harness import wait_until

from service.cli.main import main
from service.config import Settings
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.audit import audit, audit_match
from service.logs.dropped import dropped_scans
from service.logs.mcapfile import Record
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.logs.replay import replay, run_config
from service.logs.split import replay_split

pytestmark = pytest.mark.integration

STEPS = 24
BURST = range(10, 15)  # steps published back to back: the service drops scans


def record_live_run(folder: Path, workers: int) -> tuple[Path, int]:
    """Run the service with recording on, feed it, stop it; return the log and the drops."""
    port = free_port()
    settings = Settings(
        listen=[f"tcp/127.0.0.1:{port}"],
        store_dir=folder / "store",
        record_dir=folder / "logs",
        workers=workers,
        instance=f"live-{workers}",
        event_interval_s=0.0,
    )
    recorder = McapRecorder(settings.record_dir, instance=settings.instance)
    service = LocalizationService(settings, recorder=recorder).start()
    client = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    try:
        records = simulated_inputs(("r1", "r2"), steps=STEPS, seed=21)
        last = {
            r.topic.split("/")[2]: r.publish_time_ns
            for r in records
            if r.schema_name == "rlutf.LaserScan"
        }
        client.put(records[0].topic, records[0].payload)  # the map, into the embedded store
        assert wait_until(lambda: "m1" in service.maps_held(), 10.0)
        step_of = {
            r: (r.publish_time_ns - records[1].publish_time_ns) // 100_000_000 for r in records[1:]
        }
        previous = 0
        for r in records[1:]:
            if step_of[r] != previous:
                previous = step_of[r]
                time.sleep(0.0 if previous in BURST else 0.04)
            client.put(r.topic, r.payload)

        def done() -> bool:
            got = {robot: service._poses.get(robot, b"") for robot in last}
            return all(f'"stamp_ns":{last[robot]}'.encode() in p for robot, p in got.items())

        assert wait_until(done, 20.0), "the service did not answer the last scans"
    finally:
        client.close()
        service.close()
    (path,) = recorder.files
    return path, service.dispatcher.dropped


@pytest.fixture(scope="module", params=[0, 2], ids=["threads", "processes"])
def live(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Path, int]]:
    yield record_live_run(tmp_path_factory.mktemp(f"live{request.param}"), request.param)


def test_replay_reproduces_live_poses_byte_for_byte(live: tuple[Path, int], tmp_path: Path) -> None:
    log, dropped = live
    with LogFile(log) as lf:
        drop_events = [r for r in lf.messages({"rlutf.Event"}) if b"scan_dropped" in r.payload]
    assert len(drop_events) == dropped
    first = replay([log], tmp_path / "one.mcap")
    second = replay([log], tmp_path / "two.mcap")
    assert first.dropped == dropped
    for robot in ("r1", "r2"):
        recorded = [p.payload for p in first.recorded[robot]]
        assert len(recorded) >= STEPS - dropped - 2
        assert [p.payload for p in first.recomputed[robot]] == recorded
        assert [p.payload for p in second.recomputed[robot]] == recorded
    outs = [
        [r.payload for r in read_all(tmp_path / f"{n}.mcap", ["rlutf.PoseEstimate"])]
        for n in ("one", "two")
    ]
    assert outs[0] == outs[1] and len(outs[0]) == sum(len(v) for v in first.recorded.values())
    # The output is itself a valid replay input giving the same poses.
    again = replay([tmp_path / "one.mcap"])
    assert again.recomputed == first.recomputed


def test_replay_without_keeping_the_poses_audits_alike(live: tuple[Path, int]) -> None:
    """``keep=False`` (what ``rlutf replay`` runs unless it plots): the audit's counts, no pose
    held, the same verdict as the audit of the kept poses."""
    log, _ = live
    kept = replay([log])
    lean = replay([log], keep=False)
    assert not lean.recorded and not lean.recomputed and not lean.odometry
    assert lean.match.waiting() == 0  # every recorded pose found its recomputed one
    assert audit_match(lean.match) == audit(kept.recorded, kept.recomputed, kept.gap_ns)
    assert lean.match.recorded_total == sum(len(v) for v in kept.recorded.values())
    assert (lean.inputs, lean.dropped) == (kept.inputs, kept.dropped)
    # An audit alone holds the dropped scans' keys, not their Events (written only with --out);
    # a share of a split audit, only its robots'.
    with LogFile(log) as lf:
        drops, records = dropped_scans([lf], records_too=False)
        assert sum(drops.values()) == lean.dropped and records == []
        mine, _ = dropped_scans([lf], owns=lambda robot: robot == "r1")
        assert mine == Counter({k: n for k, n in drops.items() if k[0] == "r1"})
    # Split between two processes by robot (r1 and r2 apart): the same audit, drops included.
    split = replay_split([log], run_config([log]), 2, min_messages=0)
    assert audit_match(split.match) == audit_match(lean.match)
    assert (split.inputs, split.dropped, split.rejected) == (
        lean.inputs,
        lean.dropped,
        lean.rejected,
    )


def _tampered(
    log: Path, tmp_path: Path, field: str, change: Callable[[Any], Any]
) -> tuple[Path, dict[str, Any]]:
    """A copy of ``log`` with ``field`` of its middle PoseEstimate changed, and that pose."""
    with LogFile(log) as lf:
        config = lf.config()
        records = list(lf.messages())
    poses = [i for i, r in enumerate(records) if r.schema_name == "rlutf.PoseEstimate"]
    k = poses[len(poses) // 2]
    data = json.loads(records[k].payload)
    data[field] = change(data.get(field))
    changed = json.dumps(data, separators=(",", ":")).encode()
    records[k] = Record(*records[k][:2], changed, *records[k][3:])
    tampered = write_log(
        tmp_path / "tampered.mcap",
        [r for r in records if r.schema_name.startswith("rlutf.")],
        config,
    )
    return tampered, data


def test_cli_audit_passes_and_a_nudged_pose_fails(
    live: tuple[Path, int], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log, _ = live
    assert main(["replay", str(log), "--out", str(tmp_path / "ok.mcap"), "--quiet"]) == 0
    assert "audit: passed" in capsys.readouterr().out
    tampered, _ = _tampered(log, tmp_path, "x", lambda v: v + 1e-6)
    code = main(["replay", str(tampered), "--out", str(tmp_path / "t.mcap"), "--quiet"])
    out = capsys.readouterr().out
    assert code == 1 and "FAIL" in out and "audit: FAILED" in out
    assert main(["replay", str(tampered), "--quiet"]) == 1  # the audit alone: nothing written
    assert "audit: FAILED" in capsys.readouterr().out
    # ... unless the tolerance allows it
    code = main(
        [
            "replay",
            str(tampered),
            "--out",
            str(tmp_path / "t2.mcap"),
            "--quiet",
            "--tolerance",
            "1e-5",
        ]
    )
    assert code == 0


@pytest.mark.parametrize(
    ("field", "change"),
    [
        ("map_id", lambda v: "m2"),  # the robot put on another map
        ("deviation_range", lambda v: v + 0.5),  # its 95 % bound widened by half a metre
        ("covariance", lambda v: [c * 2 for c in v]),
        ("localization_score", lambda v: 1.0 - v / 2),
        ("added", lambda v: True),  # a key the service never wrote
    ],
)
def test_cli_audit_fails_on_any_field_of_a_recorded_pose_changed(
    live: tuple[Path, int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    field: str,
    change: Callable[[Any], Any],
) -> None:
    """Every field of a recorded PoseEstimate is audited, not x, y, theta and status only: a
    pose moved to another map, or shown as surer than it was, passed as "audit: passed"."""
    log, _ = live
    tampered, data = _tampered(log, tmp_path, field, change)
    for jobs in ("1", "2"):  # one process, and the audit split by robot
        assert main(["replay", str(tampered), "--quiet", "--jobs", jobs]) == 1
        out = capsys.readouterr().out
        assert "audit: FAILED" in out and "FAIL" in out
        assert f"{data['robot_id']}: recorded poses differ from the recomputed ones in {field}" in (
            " ".join(out.split())
        )
