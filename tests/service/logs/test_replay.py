"""Replay over logs written by hand (no Zenoh): determinism, drops, configuration, output."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from mcaplog_fixtures import T0, payloads, read_all, simulated_inputs, write_log

from rlutf.localizer import LocalizerConfig
from rlutf.motion import compose
from schemas import Event, EventCode, LaserScan, PoseEstimate, decode, encode
from service.cli.main import main
from service.engine import FleetEngine
from service.keys import Keys
from service.logs import mcapfile
from service.logs.mcapfile import Record
from service.logs.mcapread import LogFile
from service.logs.plots import dead_reckoning
from service.logs.replay import INPUT_MODELS, REPLAY_METADATA, pose_record, replay
from service.logs.replayconfig import ReplayConfigError, resolve
from service.maps.book import MapBook


@pytest.fixture(scope="module")
def inputs_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "inputs.mcap"
    return write_log(path, simulated_inputs())


def test_replay_without_config_uses_defaults_and_topic_prefix(tmp_path: Path) -> None:
    log = write_log(tmp_path / "in.mcap", simulated_inputs(("a",), steps=5, prefix="fleet/x"))
    result = replay([log], tmp_path / "out.mcap")
    assert result.config.prefix == "fleet/x"
    assert result.config.localizer == LocalizerConfig()
    poses = read_all(tmp_path / "out.mcap", ["rlutf.PoseEstimate"])
    assert {p.topic for p in poses} == {"fleet/x/robots/a/pose"}
    assert len(poses) == 5


def test_replay_is_deterministic_and_writes_inputs_poses_config(
    inputs_log: Path, tmp_path: Path
) -> None:
    one = replay([inputs_log], tmp_path / "one.mcap")
    two = replay([inputs_log], tmp_path / "two.mcap")
    assert sum(len(v) for v in one.recomputed.values()) == 40
    for robot in ("r1", "r2"):
        assert [p.payload for p in one.recomputed[robot]] == [
            p.payload for p in two.recomputed[robot]
        ]
    assert payloads(tmp_path / "one.mcap", "rlutf.PoseEstimate") == payloads(
        tmp_path / "two.mcap", "rlutf.PoseEstimate"
    )
    # inputs are copied unchanged, in the same order
    for schema in ("rlutf.Map", "rlutf.InitialPose", "rlutf.Odometry", "rlutf.LaserScan"):
        assert payloads(tmp_path / "one.mcap", schema) == payloads(inputs_log, schema)
    # a pose is logged at the receive time of its scan, publish time = the scan's stamp
    scans = {
        (r.topic.split("/")[2], r.publish_time_ns): r.log_time_ns
        for r in read_all(inputs_log, ["rlutf.LaserScan"])
    }
    for pose in read_all(tmp_path / "one.mcap", ["rlutf.PoseEstimate"]):
        assert scans[(pose.topic.split("/")[2], pose.publish_time_ns)] == pose.log_time_ns
    with LogFile(tmp_path / "one.mcap") as lf:
        assert lf.config() == one.config.settings
        names = [name for name, _ in lf.metadata()]
        assert REPLAY_METADATA in names


def test_replay_equals_the_engine_fed_directly(inputs_log: Path) -> None:
    """The same code path: FleetEngine fed the inputs in log order gives the same bytes."""
    result = replay([inputs_log])
    cfg = result.config
    engine = FleetEngine(Keys(cfg.prefix), cfg.localizer, cfg.event_interval_ns)
    book = MapBook(cfg.max_payload_bytes)
    expected: dict[str, list[bytes]] = {}
    for rec in read_all(inputs_log):
        if rec.schema_name == "rlutf.Map":
            loaded = book.offer("m1", rec.payload, rec.log_time_ns)
            assert loaded is not None
            engine.register_map("m1", 1, loaded.world, rec.log_time_ns)
            continue
        msg = decode(INPUT_MODELS[rec.schema_name], rec.payload)
        for out in engine.handle(rec.topic.split("/")[2], msg, rec.log_time_ns):
            if out.kind == "pose":
                expected.setdefault(pose_record(out.payload).robot, []).append(out.payload)
    assert {r: [p.payload for p in v] for r, v in result.recomputed.items()} == expected


def _drop_event(robot: str, stamp: int, log_time: int) -> Record:
    ev = Event(
        stamp_ns=stamp,
        level="info",
        code=EventCode.SCAN_DROPPED,
        key=f"rlutf/robots/{robot}/scan",
        message="replaced",
    )
    return Record(f"rlutf/robots/{robot}/events", "rlutf.Event", encode(ev), log_time, stamp)


@pytest.mark.parametrize("library", ["now", "rlutf 0.5.2"], ids=["at receipt", "older service"])
def test_recorded_drops_are_honoured(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, library: str
) -> None:
    """The service logs a drop at the dropped scan's own log_time (since 0.5.3); an older one
    logged it when the newer scan arrived, and replay drops the first scan of its stamp. The
    output, this code's log, drops it again in either case."""
    records = simulated_inputs(("r1",), steps=8)
    dropped_stamp = T0 + 4 * 100_000_000
    (scan,) = [
        r
        for r in records
        if r.schema_name == "rlutf.LaserScan" and r.publish_time_ns == dropped_stamp
    ]
    if library != "now":
        monkeypatch.setattr(mcapfile, "LIBRARY", library)
    at = scan.log_time_ns if library == "now" else T0 + 5 * 100_000_000 + 2_000_000
    with_drop = [*records, _drop_event("r1", dropped_stamp, at)]
    without_scan = [r for r in records if r is not scan]
    dropping = write_log(tmp_path / "drop.mcap", with_drop)
    missing = write_log(tmp_path / "noscan.mcap", without_scan)
    monkeypatch.undo()  # the replay's output is this code's log
    a = replay([dropping], tmp_path / "a.mcap")
    b = replay([missing])
    assert a.dropped == 1
    stamps = [p.stamp_ns for p in a.recomputed["r1"]]
    assert dropped_stamp not in stamps and len(stamps) == 7
    assert [p.payload for p in a.recomputed["r1"]] == [p.payload for p in b.recomputed["r1"]]
    # The output keeps the dropped scan and the event, so replaying it drops it again.
    again = replay([tmp_path / "a.mcap"])
    assert again.dropped == 1
    assert [p.payload for p in again.recomputed["r1"]] == [p.payload for p in a.recomputed["r1"]]


def test_of_two_scans_stamped_alike_the_one_dropped_live_is_dropped(tmp_path: Path) -> None:
    """A robot stamped two scans alike and the service dropped the second (under load): replay
    dropped the first of that stamp and computed other poses than live, so the audit of a right
    log failed (helper 51's review of robot clocks)."""
    records = simulated_inputs(("r1",), steps=8)
    scans = [r for r in records if r.schema_name == "rlutf.LaserScan"]
    first, second = scans[3], scans[4]
    msg = decode(LaserScan, second.payload)
    twin = Record(
        second.topic,
        second.schema_name,
        encode(msg.model_copy(update={"stamp_ns": first.publish_time_ns})),
        second.log_time_ns,
        first.publish_time_ns,
    )
    inputs = [twin if r is second else r for r in records]
    drop = _drop_event("r1", first.publish_time_ns, twin.log_time_ns)
    a = replay([write_log(tmp_path / "drop.mcap", [*inputs, drop])])
    b = replay([write_log(tmp_path / "noscan.mcap", [r for r in inputs if r is not twin])])
    assert a.dropped == 1
    assert [p.payload for p in a.recomputed["r1"]] == [p.payload for p in b.recomputed["r1"]]


def test_rotated_files_replay_as_one(tmp_path: Path) -> None:
    records = simulated_inputs(steps=10)
    whole = replay([write_log(tmp_path / "whole.mcap", records)])
    half = len(records) // 2
    parts = [
        write_log(tmp_path / "p1.mcap", records[:half]),
        write_log(tmp_path / "p2.mcap", records[half:]),
    ]
    # a rotated file starts with the maps recorded before it: replayed once
    parts.append(write_log(tmp_path / "p3.mcap", [records[0], *records[half + 1 :][:0]]))
    split = replay(parts, tmp_path / "split.mcap")
    assert len(payloads(tmp_path / "split.mcap", "rlutf.Map")) == 1
    assert {r: [p.payload for p in v] for r, v in split.recomputed.items()} == {
        r: [p.payload for p in v] for r, v in whole.recomputed.items()
    }


def test_config_from_log_and_overrides(tmp_path: Path) -> None:
    loc = asdict(LocalizerConfig())
    loc["epsilon"] = 0.02
    recorded = {
        "prefix": "rlutf",
        "event_interval_s": 0.5,
        "max_payload_bytes": 2_000_000,
        "localizer": loc,
        "instance": "x",
    }
    log = write_log(tmp_path / "in.mcap", simulated_inputs(("r1",), steps=3), config=recorded)
    assert replay([log]).config.localizer.epsilon == 0.02
    settings = tmp_path / "s.toml"
    settings.write_text("[localizer]\nepsilon = 0.03\ndelta = 1\n")
    cfg = replay([log], settings_file=settings, assignments=["localizer.max_rounds=2"]).config
    assert cfg.localizer.epsilon == 0.03 and cfg.localizer.max_rounds == 2
    assert isinstance(cfg.localizer.delta, float) and cfg.localizer.delta == 1.0
    assert cfg.event_interval_ns == 500_000_000 and cfg.settings["instance"] == "x"
    with pytest.raises(ReplayConfigError, match="unknown parameter"):
        resolve(recorded, assignments=["localizer.bogus=1"])
    with pytest.raises(ReplayConfigError, match="KEY=VALUE"):
        resolve(recorded, assignments=["nonsense"])
    with pytest.raises(ReplayConfigError, match="epsilon"):
        resolve(recorded, assignments=["localizer.epsilon=-1"])
    # one line naming the setting and the value, not pydantic's layout and its links
    for assignment, said in (
        ("localizer.epsilon=abc", "localizer.epsilon: Input should be a valid number"),
        ("limits.max_range=-3", "limits.max_range: Input should be greater than 0 (got -3)"),
        ('max_payload_bytes="x"', "max_payload_bytes: expected a whole number, got 'x'"),
    ):
        with pytest.raises(ReplayConfigError) as refused:
            resolve(recorded, assignments=[assignment])
        assert said in str(refused.value) and "pydantic.dev" not in str(refused.value)
        assert "\n" not in str(refused.value)
    # A misspelt setting changed nothing, and the audit passed under settings the user did not
    # get: refused, from --set and from a file alike, nested ones too.
    with pytest.raises(ReplayConfigError, match="no setting of the service is named max_map_ar"):
        resolve(recorded, assignments=["max_map_areaa=5"])
    with pytest.raises(ReplayConfigError, match=r"named limits\.max_rangee"):
        resolve(recorded, assignments=["limits.max_rangee=5"])
    typo = tmp_path / "typo.json"
    typo.write_text('{"foo": 1}')
    with pytest.raises(
        ReplayConfigError, match=r"typo.json: no setting of the service is named foo"
    ):
        resolve(recorded, settings_file=typo)
    # a setting of the service's that a replay does not use (as in the file serve reads) is let
    # through, and a file that is not text is named
    assert resolve(recorded, assignments=["listen=[]"]).settings["listen"] == []
    junk = tmp_path / "junk.json"
    junk.write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(ReplayConfigError, match=r"junk\.json: not UTF-8 text"):
        resolve(recorded, settings_file=junk)


def test_invalid_inputs_are_rejected_not_fatal(tmp_path: Path) -> None:
    records = simulated_inputs(("r1",), steps=4)
    bad = Record(
        "rlutf/robots/r1/scan",
        "rlutf.LaserScan",
        b'{"stamp_ns": "x"}',
        records[-1].log_time_ns + 1,
        0,
    )
    result = replay([write_log(tmp_path / "in.mcap", [*records, bad])])
    assert result.rejected == 1
    assert len(result.recomputed["r1"]) == 4


def test_replay_metadata_names_inputs(inputs_log: Path, tmp_path: Path) -> None:
    replay([inputs_log], tmp_path / "o.mcap", assignments=["localizer.seed=1"])
    with LogFile(tmp_path / "o.mcap") as lf:
        meta = dict(lf.metadata())[REPLAY_METADATA]
        assert json.loads(meta["inputs"]) == [str(inputs_log)]
        assert json.loads(meta["assignments"]) == ["localizer.seed=1"]
        assert lf.config() is not None and lf.config()["localizer"]["seed"] == 1  # type: ignore[index]
    assert not (tmp_path / "o.mcap.part").exists()


def test_dead_reckoning_anchors_odometry_at_the_initial_pose() -> None:
    truth = np.array([[1.0 + 0.1 * i, 2.0 + 0.05 * i * i, 0.2 * i] for i in range(10)])
    frame = np.array([-5.0, 3.0, 1.1])  # the odometry frame's origin is irrelevant
    odom = [(i, *compose(frame, p)) for i, p in enumerate(truth)]
    start = [(0, "m1", *truth[0])]
    assert np.allclose(dead_reckoning(odom, start), truth, atol=1e-12)
    # re-anchored at a second initial pose
    moved = (5, "m1", 0.0, 0.0, 0.0)
    dr = dead_reckoning(odom, [*start, moved])
    assert np.allclose(dr[5], [0.0, 0.0, 0.0]) and np.allclose(dr[:5], truth[:5])
    assert len(dead_reckoning(odom, [])) == 0


def test_cli_replay_writes_plots(
    inputs_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["replay", str(inputs_log), "--out", str(tmp_path / "o.mcap"), "--quiet"]
    assert main([*argv, "--plot", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert "nothing to audit" in out
    for robot in ("r1", "r2"):
        png = tmp_path / "plots" / f"{robot}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert main([*argv, "--set", "localizer.bogus=1"]) == 2
    assert "unknown parameter" in capsys.readouterr().err
    # outputs that cannot be written are refused before the replay, not after it
    for flag, where in (("--out", tmp_path / "no" / "o.mcap"), ("--plot", inputs_log)):
        assert main(["replay", str(inputs_log), flag, str(where), "--quiet"]) == 2
        assert flag in capsys.readouterr().err
    # a tolerance that cannot be one is refused before any work, not a FAILED audit
    for flag, value in (
        ("--tolerance", "-1"),
        ("--tolerance", "nan"),
        ("--heading-tolerance", "-1"),
    ):
        with pytest.raises(SystemExit) as exit_:
            main(["replay", str(inputs_log), flag, value, "--quiet"])
        assert exit_.value.code == 2 and flag in capsys.readouterr().err
    assert main(["replay", str(inputs_log), "--out", str(inputs_log), "--quiet"]) == 2


def test_every_pose_carries_its_covariance(inputs_log: Path, tmp_path: Path) -> None:
    result = replay([inputs_log], tmp_path / "out.mcap")
    poses = [
        decode(PoseEstimate, p.payload) for records in result.recomputed.values() for p in records
    ]
    assert poses
    for pose in poses:
        assert pose.covariance is not None and len(pose.covariance) == 9
        cov = np.array(pose.covariance).reshape(3, 3)
        np.testing.assert_array_equal(cov, cov.T)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        # 120 beams: millimetres to a centimetre
        assert 1e-4 < np.sqrt(cov[0, 0] + cov[1, 1]) < 0.02


def test_poses_deleted_long_before_the_log_ends_fail_the_audit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pose the log lacks counts as unverified only near the log's end, where a crash cuts a
    log short. Before, a log with all of one robot's poses deleted audited as passed (each
    "unverified"), and so did one with a robot's poses deleted from some time on."""
    honest = tmp_path / "honest.mcap"
    replay([write_log(tmp_path / "in.mcap", simulated_inputs(steps=400))], honest)
    records = read_all(honest)
    end, sec = records[-1].log_time_ns, 10**9

    def without(name: str, gone: Callable[[Record], bool]) -> str:
        kept = [r for r in records if not (r.schema_name == "rlutf.PoseEstimate" and gone(r))]
        assert len(kept) < len(records)
        return str(
            write_log(tmp_path / name, [r for r in kept if r.schema_name.startswith("rlutf.")])
        )

    assert main(["replay", str(honest), "--quiet"]) == 0
    every = without("no-r2.mcap", lambda r: "/r2/" in r.topic)  # 40 s of poses
    since = without("r2-cut.mcap", lambda r: "/r2/" in r.topic and r.log_time_ns > end - 35 * sec)
    tail = without("r2-tail.mcap", lambda r: "/r2/" in r.topic and r.log_time_ns > end - 2 * sec)
    capsys.readouterr()
    for log in (every, since):
        for jobs in ("1", "2"):
            assert main(["replay", log, "--quiet", "--jobs", jobs]) == 1
            out = capsys.readouterr().out
            assert "audit: FAILED" in out and "│ r2 " in out
    # The last seconds' poses missing, as after a crash: reported, not a failure.
    assert main(["replay", tail, "--quiet"]) == 0
    assert "audit: passed" in capsys.readouterr().out
    assert main(["replay", tail, "--quiet", "--strict"]) == 1
