"""An audit never passes over a record it did not read.

The logs are recorded by the service's own recorder (:class:`McapRecorder`), from simulated
inputs and the poses the engine computes for them; the files made of them are written as
another tool, a salvage or tampering would write them: by ``rlutf log recover`` from a damaged
copy, or by the ``mcap`` library's own writer. Robot ``r3`` starts late, so that its channels are
declared in later chunks than the schemas they name.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Schema
from mcap.writer import Writer
from mcaplog_fixtures import (
    add_outside_chunks,
    read_all,
    record_with_poses,
    simulated_inputs,
    unindex_last_chunk,
)
from service_harness import wait_until

from service.cli.main import main
from service.logs.completeness import SHOWN, Completeness, FileCheck, check_run
from service.logs.manifest import MANIFEST_METADATA, RECOVERED_METADATA, Manifest, Recovered
from service.logs.mcapchunks import unpack_chunk
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.logs.mcaprecords import read_records
from service.logs.replay import replay
from service.logs.runs import group_runs, run_tag
from service.logs.split import replay_split


def _inputs(seed: int = 2, steps: int = 12) -> list[Any]:
    records = simulated_inputs(("r1", "r2", "r3"), seed=seed, steps=steps, beams=90)
    late = records[len(records) // 2].log_time_ns
    return [
        r
        for r in records
        if "/r3/" not in r.topic or r.log_time_ns >= late or r.schema_name == "rlutf.InitialPose"
    ]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One run of three robots, recorded in small chunks into one file."""
    folder = tmp_path_factory.mktemp("recorded")
    rec = record_with_poses(folder / "logs", folder, _inputs(), instance="demo", chunk_size=4096)
    (path,) = rec.files
    return path


def _audit(capsys: pytest.CaptureFixture[str], *paths: Path, jobs: int = 1) -> tuple[int, str, str]:
    code = main(["replay", *map(str, paths), "--quiet", "--jobs", str(jobs)])
    out, err = capsys.readouterr()
    return code, out, err


def _copy(
    src: Path,
    dst: Path,
    schemaless: Callable[[str], bool] = lambda topic: False,
    loose: Callable[[str], bool] = lambda topic: False,
    keep: Callable[[str], bool] = lambda topic: True,
    edit: Callable[[str, bytes], bytes] = lambda topic, data: data,
    metadata: Callable[[str, dict[str, str]], dict[str, str] | None] = lambda n, d: d,
    unindexed: Callable[[str], bool] = lambda topic: False,
) -> Path:
    """``src`` written again by the ``mcap`` library's writer, as another tool would: channels
    on the topics ``schemaless`` picks registered without their schema (a salvage that lost it),
    messages on those ``loose`` picks written outside chunks (a writer may write them beside
    indexed chunks), each in a chunk of its own that the chunk index leaves out where
    ``unindexed`` picks it, those ``keep`` refuses left out, payloads passed through ``edit``;
    the metadata records copied (the manifest among them) as ``metadata`` gives them (``None``:
    left out)."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        writer = Writer(out, chunk_size=4096)
        writer.start("", "another tool")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            topic = channel.topic
            if not keep(topic):
                continue
            assert schema is not None
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                named = 0 if schemaless(topic) else schemas[schema.id]
                channels[channel.id] = writer.register_channel(
                    topic, channel.message_encoding, named
                )
            args = (channels[channel.id], message.log_time, edit(topic, message.data))
            if loose(topic):
                add_outside_chunks(writer, *args, message.publish_time)
                continue
            if unindexed(topic):
                writer.flush()  # a chunk of its own
            writer.add_message(*args, message.publish_time)
            if unindexed(topic):
                unindex_last_chunk(writer)
        for record in reader.iter_metadata():
            data = metadata(record.name, dict(record.metadata))
            if data is not None:
                writer.add_metadata(record.name, data)
        writer.finish()
    return dst


def _moving(path: Path) -> Callable[[str, bytes], bytes]:
    """An ``edit`` that moves the third pose of ``r1`` in ``path`` by 25 cm."""
    poses = [r for r in read_all(path, ["rlutf.PoseEstimate"]) if "/r1/" in r.topic]
    stamp = poses[2].publish_time_ns

    def edit(topic: str, data: bytes) -> bytes:
        if topic != "rlutf/robots/r1/pose" or json.loads(data)["stamp_ns"] != stamp:
            return data
        pose = json.loads(data)
        pose["x"] += 0.25
        return json.dumps(pose).encode()

    return edit


# ------------------------------------------------------------------ channels without a schema


def _schema_chunks(path: Path) -> list[tuple[int, int]]:
    """Where the chunks that declare a schema start, and their data's length."""
    found = []
    with open(path, "rb") as f:
        for at, record in read_records(f, magic=True):
            if isinstance(record, Chunk) and any(
                isinstance(r, Schema) for r in unpack_chunk(record)
            ):
                found.append((at, len(record.data)))
    return found


def test_a_log_recovered_without_its_schemas_is_counted_and_its_audit_is_incomplete(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording cut by a crash whose chunks that declare the schemas are damaged: ``rlutf log
    recover`` copies the channels declared later without a schema. Replay skipped their
    messages, found no recorded pose and said "nothing to audit", exit 0."""
    data = bytearray(recorded.read_bytes())
    for at, length in _schema_chunks(recorded):
        middle = at + 60 + length // 2
        data[middle : middle + 16] = bytes(16)  # as a disk error would
    part = tmp_path / (recorded.name + ".part")
    part.write_bytes(bytes(data[:-300]))  # and cut short, as a crash leaves it
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(part), str(fixed)]) == 0
    capsys.readouterr()
    with LogFile(fixed) as lf:
        bare = {c.topic: c.messages for c in lf.channels() if not c.schema_name}
        recovered = [d for n, d in lf.metadata() if n == RECOVERED_METADATA]
    assert "rlutf/robots/r3/pose" in bare and all(bare.values())
    assert recovered and int(recovered[0]["bad_chunks"]) > 0
    assert main(["log", "info", str(fixed), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["unread"] == bare
    assert info["recovered"][0]["source"] == part.name
    assert main(["log", "info", str(fixed)]) == 0
    out = capsys.readouterr().out
    assert "channels without a schema not read" in out and "could not copy" in out
    code, out, err = _audit(capsys, fixed)
    assert code == 2, out + err
    assert "audit: incomplete" in out
    assert "nothing to audit" not in out and "audit: passed" not in out
    assert "rlutf/robots/r3/pose" in out and "audit an undamaged copy" in out


def test_a_robot_whose_channels_lost_their_schema_is_not_audited_and_said_so(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Another tool's salvage that wrote r3's channels without their schema: replay audited r1
    and r2 and passed, with r3 left out and nothing said. Now r3 is named incomplete and the
    others audited; a pose of r1 moved still fails the audit (a tamper alarm is no less one
    beside what could not be read)."""
    log = _copy(recorded, tmp_path / "bare.mcap", schemaless=lambda t: "/r3/" in t)
    code, out, _ = _audit(capsys, log)
    assert code == 2 and "audit: incomplete" in out and "the other robots passed" in out
    assert "r3/scan" in out and "channels without a schema not read" in out
    assert "changed after it was recorded" not in out  # not read is no alteration
    moved = _copy(
        recorded, tmp_path / "moved.mcap", schemaless=lambda t: "/r3/" in t, edit=_moving(recorded)
    )
    code, out, _ = _audit(capsys, moved)
    assert code == 1 and "audit: FAILED" in out
    # a pose moved of a robot not read whole makes it no more than incomplete
    both = _copy(
        recorded,
        tmp_path / "both.mcap",
        schemaless=lambda t: "/r1/" in t or "/r3/" in t,
        edit=_moving(recorded),
    )
    code, out, _ = _audit(capsys, both)
    assert code == 2 and "audit: incomplete" in out


# ------------------------------------------------------------------ messages outside chunks


def test_messages_outside_the_indexed_chunks_are_read_and_audited(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An indexed file whose r3 messages lie outside chunks, or in chunks its chunk index leaves
    out: they were skipped, as the ``mcap`` library's indexed reader skips them, and the audit
    passed without r3. Now they are read, in log-time order, and audited."""
    original = read_all(recorded)
    for name, how in (("loose", "loose"), ("unindexed", "unindexed")):
        log = _copy(recorded, tmp_path / f"{name}.mcap", **{how: lambda t: "/r3/" in t})
        with open(log, "rb") as f:
            indexed = sum(1 for _ in make_reader(f).iter_messages())
        assert indexed < len(original)  # what the library's indexed reader gives
        assert read_all(log) == original
        code, out, _ = _audit(capsys, log)
        assert code == 0 and "audit: passed" in out
        assert "│ r3 " in out  # audited
    moved = _copy(
        recorded, tmp_path / "moved.mcap", loose=lambda t: "/r1/" in t, edit=_moving(recorded)
    )
    code, out, _ = _audit(capsys, moved)
    assert code == 1 and "audit: FAILED" in out


# ------------------------------------------------------------------ the recorder's manifest


def test_the_recorder_lists_each_files_messages_as_it_finishes_it(tmp_path: Path) -> None:
    rec = record_with_poses(
        tmp_path / "logs", tmp_path, _inputs(), instance="demo", chunk_size=4096, max_bytes=15_000
    )
    assert len(rec.files) >= 3
    manifests = []
    for k, path in enumerate(rec.files):
        with LogFile(path) as lf:
            tag = run_tag(lf)
            (data,) = [d for n, d in lf.metadata() if n == MANIFEST_METADATA]
            manifest = Manifest.from_metadata(data)
            assert manifest is not None and tag is not None
            assert (manifest.run_id, manifest.sequence) == (rec.run_id, k)
            assert (tag.run_id, tag.sequence) == (rec.run_id, k)
            assert tag.follows == (k - 1 if k else None)
            read = {(c.topic, c.schema_name, c.messages) for c in lf.channels() if c.messages}
            assert set(manifest.messages) == read
            manifests.append(manifest)
    assert [m.last for m in manifests] == [False] * (len(manifests) - 1) + [True]


def test_a_run_that_stops_with_no_file_open_ends_with_a_file_that_says_so(tmp_path: Path) -> None:
    """The last file rotated, nothing recorded since: the stop writes a file of the run's maps
    alone, whose manifest says the run ended there (else its last file says more followed)."""
    rec = McapRecorder(tmp_path, instance="demo", max_seconds=0.5)
    for r in _inputs(steps=3):  # in a few milliseconds: all into the first file
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    assert wait_until(lambda: rec.files)  # rotated half a second after it opened
    rec.close()
    assert len(rec.files) == 2
    with LogFile(rec.files[1]) as lf:
        assert {c.schema_name for c in lf.channels()} == {"rlutf.Map"}
    with LogFile(rec.files[0]) as first, LogFile(rec.files[1]) as end:
        for lf in (first, end):
            list(lf.messages())
        whole = check_run([first, end])
    assert not whole.incomplete and whole.last is not None and whole.last.manifest is not None
    assert whole.last.manifest.last


def _rotated(tmp_path: Path) -> McapRecorder:
    return record_with_poses(
        tmp_path / "logs", tmp_path, _inputs(), instance="demo", chunk_size=4096, max_bytes=15_000
    )


def test_a_file_of_the_run_left_out_makes_its_audit_incomplete(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The run's last file left out was not seen at all (the audit passed); a file in the
    middle was named in a warning and the audit went on to pass or fail by chance."""
    files = _rotated(tmp_path).files
    code, out, _ = _audit(capsys, *files)
    assert code == 0 and "audit: passed" in out and "rlutf.manifest" not in out
    code, out, _ = _audit(capsys, *files[:-1])
    assert code == 2 and "audit: incomplete" in out
    assert f"file {len(files) - 2} of the run, was followed by another" in out
    code, out, _ = _audit(capsys, files[0], *files[2:])
    assert code == 2 and "audit: incomplete" in out and "file(s) 1 of the run are not given" in out
    assert main(["log", "info", *map(str, files[:-1]), "--json"]) == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    assert [n["kind"] for n in run["notes"]] == ["incomplete"]
    # beside a run read whole: no alarm, no pass
    code, out, _ = _audit(capsys, recorded, *files[:-1])
    assert code == 2 and "audit: incomplete: 1 run(s) not read whole; 1 run(s) passed" in out


def test_a_robot_removed_from_a_finished_file_fails_its_audit(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every record of r3 removed (``mcap filter`` by topic, its metadata kept): the audit
    of r1 and r2 passed. The file's manifest lists r3's messages, which are not there."""
    log = _copy(recorded, tmp_path / "no-r3.mcap", keep=lambda t: "/r3/" not in t)
    code, out, _ = _audit(capsys, log)
    assert code == 1 and "audit: FAILED" in out
    assert "changed after it was recorded" in out and "for robot(s) r3" in out
    assert main(["log", "info", str(log), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {d[0] for d in info["manifest"]["differs"]} == {
        f"rlutf/robots/r3/{leaf}" for leaf in ("initialpose", "odom", "scan", "pose")
    }


def test_a_log_without_manifests_audits_as_before_and_says_the_check_was_not_possible(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Logs written before the recorder wrote manifests (or by another tool): the same run, its
    metadata but the manifests, its last file left out, passes as it did, with a note."""
    files = _rotated(tmp_path).files
    old = tmp_path / "old"
    old.mkdir()
    copies = [_strip(path, old / path.name) for path in files]
    code, out, _ = _audit(capsys, *copies[:-1])
    assert code == 0 and "audit: passed" in out
    assert "no rlutf.manifest" in out and "cannot be checked" in out


def _strip(src: Path, dst: Path) -> Path:
    """``src`` without its manifest, and its ``rlutf.run`` without ``follows``: as written
    before them."""

    def older(name: str, data: dict[str, str]) -> dict[str, str] | None:
        return (
            None if name == MANIFEST_METADATA else {k: v for k, v in data.items() if k != "follows"}
        )

    return _copy(src, dst, metadata=older)


def test_a_split_audit_says_incomplete_as_one_process_does(recorded: Path, tmp_path: Path) -> None:
    log = _copy(recorded, tmp_path / "bare.mcap", schemaless=lambda t: "/r3/" in t)
    one = replay([log], keep=False)
    (run,) = group_runs([log])
    split = replay_split(run.files, one.config, 2, min_messages=0)
    assert split.completeness == one.completeness and split.completeness.incomplete
    assert split.completeness.affected() == frozenset({"r3"})


def test_a_copy_of_a_log_cut_by_a_crash_audits_as_before_and_says_what_it_lacks(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording cut short by a crash (its last chunk half written, no manifest yet), then
    recovered: the audit passes as before (the tail rule covers the cut), and says so."""
    part = tmp_path / (recorded.name + ".part")
    with open(recorded, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    last = summary.chunk_indexes[-1]
    part.write_bytes(recorded.read_bytes()[: last.chunk_start_offset + last.chunk_length // 2])
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(part), str(fixed)]) == 0
    capsys.readouterr()
    code, out, _ = _audit(capsys, fixed)
    assert code == 0 and "audit: passed" in out
    assert "from a file cut short at byte" in out
    assert "salvaged by rlutf log recover from a file its recorder never finished" in out


def test_the_records_read_back_as_written_and_say_a_loss_when_malformed() -> None:
    manifest = Manifest("run", 3, False, (("rlutf/robots/r1/scan", "rlutf.LaserScan", 12),))
    assert Manifest.from_metadata(manifest.to_metadata()) == manifest
    for field, value in (("messages", "[[1, 2, 3]]"), ("last", "maybe"), ("sequence", "-1")):
        assert Manifest.from_metadata(manifest.to_metadata() | {field: value}) is None
    recovered = Recovered("x.mcap.part", False, 1234, 1, 0, 5)
    assert Recovered.from_metadata(recovered.to_metadata()) == recovered
    whole = Recovered("x.mcap.part", True, None, 0, 0, 0)
    assert not Recovered.from_metadata(whole.to_metadata()).lost_inside
    assert Recovered.from_metadata(whole.to_metadata() | {"bad_chunks": "many"}).lost_inside


def test_what_a_run_of_many_files_lacks_is_said_in_a_bounded_number_of_lines() -> None:
    """A run of weeks has thousands of files: a note per file would bury the verdict."""
    files = tuple(
        FileCheck(Path(f"f{k}.mcap"), k + 1, unread=(("rlutf/robots/r1/scan", 2),))
        for k in range(1000)
    )
    whole = Completeness(files, missing=(0,), checked=True)
    notes = whole.notes()
    assert len(notes) <= SHOWN + 3
    assert any("994 more file(s) hold 1988 message(s)" in text for _, text in notes)
    assert whole.incomplete and whole.affected() is None  # a file not given: any robot
    assert Completeness(files[:2]).affected() == frozenset({"r1"})
