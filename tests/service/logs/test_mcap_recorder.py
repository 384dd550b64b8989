"""The MCAP recorder: layout, rotation, flushing, overflow, config in every file."""

from __future__ import annotations

import json
import threading
import time
from importlib import metadata
from io import BytesIO
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcaplog_fixtures import read_all, simulated_inputs

from schemas import SCHEMA_NAMES, Event, EventCode, decode
from service.logs import mcaplog, recqueue
from service.logs.mcapfile import (
    CONFIG_KEY,
    CONFIG_METADATA,
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    LogWriter,
    Record,
    schema_data,
)
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.logs.runs import group_runs, run_tag
from service.logs.salvage import recover

CONFIG = {"prefix": "rlutf", "instance": "t1", "localizer": {"epsilon": 0.006}}
REPO = Path(__file__).resolve().parents[3]


def _record_all(rec: McapRecorder, records: list[Record]) -> None:
    for r in records:
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)


def test_writer_layout_matches_wire_md() -> None:
    buf = BytesIO()
    writer = LogWriter(buf)
    writer.write_config(CONFIG)
    inputs = simulated_inputs(("r1",), steps=2)
    writer.write_all(inputs)
    writer.finish()
    reader = make_reader(BytesIO(buf.getvalue()))
    summary = reader.get_summary()
    assert summary is not None
    for schema in summary.schemas.values():
        assert schema.encoding == SCHEMA_ENCODING
        assert schema.name in SCHEMA_NAMES.values()
        assert schema.data == (REPO / "schemas" / "jsonschema" / f"{schema.name}.json").read_bytes()
    for channel in summary.channels.values():
        assert channel.message_encoding == MESSAGE_ENCODING
    got = [(c.topic, m.log_time, m.publish_time, m.data) for _, c, m in reader.iter_messages()]
    assert got == [(r.topic, r.log_time_ns, r.publish_time_ns, r.payload) for r in inputs]
    meta = list(reader.iter_metadata())
    assert [m.name for m in meta] == [CONFIG_METADATA]
    assert json.loads(meta[0].metadata[CONFIG_KEY]) == CONFIG
    assert summary.chunk_indexes and all(c.compression == "zstd" for c in summary.chunk_indexes)
    assert schema_data("nope.Thing") is None
    # the header names the code that wrote the log, version included, for audits
    assert reader.get_header().library == f"rlutf {metadata.version('rlutf')}"


def test_recorder_writes_part_then_renames_with_instance_name(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, instance="node-a", flush_interval_s=0.1)
    rec.set_config(CONFIG)
    inputs = simulated_inputs(steps=3)
    _record_all(rec, inputs)
    deadline = time.monotonic() + 5
    while rec.current_path is None and time.monotonic() < deadline:
        time.sleep(0.01)
    part = rec.current_path
    assert part is not None and part.name.endswith(".mcap.part") and "node-a" in part.name
    rec.close()
    assert rec.files == [part.with_name(part.name.removesuffix(".part"))]
    assert not part.exists() and not list(tmp_path.glob("*.part"))
    assert rec.overflowed == 0
    got = read_all(rec.files[0], {r.schema_name for r in inputs})
    assert got == inputs
    with LogFile(rec.files[0]) as lf:
        assert lf.config() == CONFIG
    rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b"{}", 1, 1)  # after close: ignored
    rec.close()


def test_rotation_by_size_keeps_config_and_maps_in_every_file(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, instance="n", max_bytes=20_000, chunk_size=4096)
    rec.set_config(CONFIG)
    inputs = simulated_inputs(steps=40)
    _record_all(rec, inputs)
    rec.close()
    assert len(rec.files) >= 3
    total = []
    for sequence, path in enumerate(rec.files):
        with LogFile(path) as lf:
            assert lf.config() == CONFIG
            # every file names its run and its place in it (WIRE.md v1.2)
            tag = run_tag(lf)
            assert tag is not None
            assert (tag.run_id, tag.instance, tag.sequence) == (rec.run_id, "n", sequence)
            assert tag.started_ns == rec.started_ns
            maps = list(lf.messages({"rlutf.Map"}))
            assert [m.payload for m in maps][:1] == [inputs[0].payload]
            total += [r for r in lf.messages() if r.schema_name != "rlutf.Map"]
    assert [r for r in total if r.schema_name.startswith("rlutf.")] == inputs[1:]


def test_rotation_by_duration(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, max_seconds=0.3, flush_interval_s=0.05)
    rec.set_config(CONFIG)
    for i in range(8):
        rec.record("rlutf/events", "rlutf.Event", b'{"stamp_ns":1}', i, i)
        time.sleep(0.1)
    rec.close()
    assert len(rec.files) >= 2
    assert all(p.name.startswith("rlutf-2") for p in rec.files)  # no instance: rlutf-{UTC}
    assert sum(len(read_all(p)) for p in rec.files) == 8


def test_open_file_is_flushed_so_a_crash_loses_at_most_the_interval(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, flush_interval_s=0.2)
    inputs = simulated_inputs(("r1",), steps=5)
    _record_all(rec, inputs)
    time.sleep(0.6)
    part = rec.current_path
    assert part is not None
    crashed = tmp_path / "crashed.mcap.part"  # what a crash now would leave
    crashed.write_bytes(part.read_bytes())
    report = recover(crashed, tmp_path / "recovered.mcap")
    assert not report.complete
    assert read_all(tmp_path / "recovered.mcap", {r.schema_name for r in inputs}) == inputs
    rec.close()


def _stall(rec: McapRecorder) -> threading.Event:
    """Stall the writer thread before each batch it writes until the returned event is set."""
    gate = threading.Event()
    write = rec._write

    def slow(batch: list[Any]) -> bool:
        gate.wait(10)
        return write(batch)

    rec._write = slow  # type: ignore[method-assign]
    return gate


def _held_by_writer(rec: McapRecorder) -> None:
    """Wait until the stalled writer has taken what was queued (the config item) and waits."""
    deadline = time.monotonic() + 5
    while not rec._queue.empty() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_overflow_is_counted_never_blocks_and_is_logged(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, queue_size=5, foxglove=False)
    gate = _stall(rec)
    published: list[Event] = []
    rec.on_event = published.append
    rec.set_config(CONFIG)
    _held_by_writer(rec)
    t0 = time.perf_counter()
    for i in range(100):
        rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', i + 1, i)
    assert time.perf_counter() - t0 < 0.5
    assert rec.overflowed == 95
    gate.set()
    rec.close()
    events = [decode(Event, r.payload) for r in read_all(rec.files[0], ["rlutf.Event"])]
    assert [e.code for e in events] == [EventCode.RECORDER_OVERFLOW]
    assert "95 messages" in events[0].message
    assert events[0].stamp_ns == 6  # when the first was lost (its log time): a gap's start
    assert published == events
    assert len(read_all(rec.files[0], ["rlutf.Odometry"])) == 5


def test_large_messages_are_bounded_in_bytes_not_only_in_count(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A flood of scans at the message limit (1 MB) must not fill a queue of 20,000 messages.
    monkeypatch.setattr(recqueue, "LARGE_QUEUED", 3 * recqueue.LARGE)
    rec = McapRecorder(tmp_path, queue_size=1000, foxglove=False)
    gate = _stall(rec)
    rec.set_config(CONFIG)
    _held_by_writer(rec)
    big = b"{" + b" " * (recqueue.LARGE - 2) + b"}"
    for i in range(5):
        rec.record("rlutf/robots/r1/scan", "rlutf.LaserScan", big, i + 1, i)
    for i in range(5):  # small messages still go in
        rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', i + 10, i)
    assert rec.overflowed == 2 and rec.queued == 8
    gate.set()
    assert wait_drained(rec)
    rec.record("rlutf/robots/r1/scan", "rlutf.LaserScan", big, 20, 20)  # room again
    assert rec.overflowed == 2
    rec.close()
    assert len(read_all(rec.files[0], ["rlutf.LaserScan"])) == 4


def test_queued_is_the_queue_depth_and_drains_to_zero(tmp_path: Path) -> None:
    rec = McapRecorder(tmp_path, queue_size=50, foxglove=False)
    gate = _stall(rec)
    rec.set_config(CONFIG)
    _held_by_writer(rec)
    assert rec.queued == 0
    for i in range(7):
        rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', i + 1, i)
    assert rec.queued == 7
    gate.set()
    assert wait_drained(rec)
    rec.close()
    assert rec.queued == 0


def wait_drained(rec: McapRecorder, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while rec.queued and time.monotonic() < deadline:
        time.sleep(0.01)
    return rec.queued == 0


def test_null_recorder_has_nothing_queued() -> None:
    from service.logs.recording import NullRecorder

    assert NullRecorder().queued == 0


def _until(what: Any, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not what():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_a_recorder_that_cannot_write_says_so_counts_what_it_drops_and_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its folder gone (as a full disk, a real write error): one Event ``recording_failed``,
    no file opened per message meanwhile, every message not logged counted; once it can write
    again, recording resumes with an Event that says how many were not logged, in the log."""
    monkeypatch.setattr(mcaplog, "RETRY_S", 0.3)
    folder = tmp_path / "logs"
    rec = McapRecorder(folder, instance="t1", max_seconds=0.2, flush_interval_s=0.05)
    published: list[Event] = []
    rec.on_event = published.append
    rec.set_config(CONFIG)
    sent = 0

    def odometry(n: int, pause: float = 0.01) -> None:
        nonlocal sent
        for _ in range(n):
            sent += 1
            rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', sent, sent)
            time.sleep(pause)

    odometry(10)
    _until(lambda: rec.files)  # one file finished by its age
    saved = tmp_path / "saved"
    folder.rename(saved)  # the open file's rename, then every open, fails
    odometry(60)
    _until(lambda: EventCode.RECORDING_FAILED in [e.code for e in published])
    assert rec.unrecorded > 0
    assert not folder.exists()  # nothing recreated it behind the operator's back
    folder.mkdir()
    _until(lambda: odometry(5) or EventCode.RECORDING_RESUMED in [e.code for e in published])
    rec.close()
    codes = [e.code for e in published]
    assert codes == [EventCode.RECORDING_FAILED, EventCode.RECORDING_RESUMED], codes
    assert rec.errors >= 2  # failed again on each retry while the folder was gone
    failed, resumed = published
    assert failed.level == "error" and str(folder) in failed.message
    assert f"{rec.unrecorded} messages were not logged" in resumed.message
    assert resumed.stamp_ns <= failed.stamp_ns  # stamped when the gap began, for replay
    after = [f for f in rec.files if f.parent == folder and f.exists()]
    logged = [decode(Event, r.payload) for f in after for r in read_all(f, ["rlutf.Event"])]
    assert logged == [resumed]  # the gap is in the audit trail
    assert sum(len(read_all(f, ["rlutf.Odometry"])) for f in after) > 0
    assert not list(folder.glob("*.part"))  # no empty file left per retry
    # The stretch not logged takes a number of the run that no file has: the file after it
    # says so (``follows``), so the log tools name a recording gap, not a file left out.
    (run,) = group_runs([*sorted(saved.glob("*.mcap")), *after])
    assert run.skipped and not run.missing
    # The retries took no file number: the files' names go on from where the folder was left.
    numbers = [int(f.name[-8:-5]) for f in [*sorted(saved.glob("*.mcap")), *after]]
    assert numbers == list(range(1, len(numbers) + 1)), numbers


def test_a_gap_that_ends_just_before_the_stop_is_marked_in_the_last_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Recording resumed but no flush yet when the service stops: the file finished at the stop
    still starts the resumed stretch with ``recording_resumed`` (else replay would compare the
    poses after the gap and fail)."""
    monkeypatch.setattr(mcaplog, "RETRY_S", 0.2)
    folder = tmp_path / "logs"
    rec = McapRecorder(folder, instance="t1", flush_interval_s=60.0)  # no flush but at the stop
    published: list[Event] = []
    rec.on_event = published.append
    rec.set_config(CONFIG)
    rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', 1, 1)
    _until(lambda: rec.current_path is not None)
    folder.rename(tmp_path / "gone")  # the open file can no longer be renamed when finished
    rec.max_seconds = 0.0  # finish it at the next rotation check
    _until(lambda: bool(published))  # recording_failed
    rec.max_seconds = 3600.0
    folder.mkdir()
    time.sleep(0.3)  # past the retry delay
    rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', 3, 3)
    _until(lambda: rec.current_path is not None)
    rec.close()
    assert [e.code for e in published] == [
        EventCode.RECORDING_FAILED,
        EventCode.RECORDING_RESUMED,
    ]
    (last,) = [f for f in rec.files if f.parent == folder]
    logged = [decode(Event, r.payload).code for r in read_all(last, ["rlutf.Event"])]
    assert logged == [EventCode.RECORDING_RESUMED]
    assert len(read_all(last, ["rlutf.Odometry"])) == 1
