"""A log from elsewhere may hold anything: the log tools read it to the end, whatever its
payloads hold. A payload nested past the JSON parser's depth (100,000 brackets, a few hundred
kilobytes) in an Event, a Map or a pose crashed ``rlutf log info``, ``rlutf replay`` and
``rlutf log views`` with an "unexpected error" (a RecursionError, to be reported as a bug)."""

from __future__ import annotations

import json
import os
import tracemalloc
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import IndexType
from mcap.writer import Writer as McapWriter
from mcaplog_fixtures import simulated_inputs, write_log

from service.cli.main import main
from service.logs.mcapfile import Record
from service.logs.mcapread import LogFile, RedeclaredLog, merged_messages
from service.logs.replay import replay
from service.logs.salvage import recover

DEEP = b"[" * 100_000 + b"]" * 100_000


@pytest.fixture
def hostile(tmp_path: Path) -> Path:
    """A run's inputs, then an Event, a Map and a pose that are nothing but brackets."""
    records = list(simulated_inputs(seed=1, steps=5, beams=90))
    t = records[-1].log_time_ns
    records += [
        Record("rlutf/robots/r0/events", "rlutf.Event", DEEP, t + 1, t + 1),
        Record("rlutf/maps/m9", "rlutf.Map", DEEP, t + 2, t + 2),
        Record("rlutf/robots/r0/pose", "rlutf.PoseEstimate", DEEP, t + 3, t + 3),
    ]
    return write_log(tmp_path / "hostile.mcap", records)


def test_the_log_tools_read_a_log_with_payloads_nested_past_the_parsers_depth(
    hostile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["log", "info", str(hostile)]) == 0
    assert main(["log", "views", str(hostile), "--out", str(tmp_path / "views.mcap")]) == 0
    code = main(["replay", str(hostile), "--out", str(tmp_path / "re.mcap"), "--quiet"])
    out, err = capsys.readouterr()
    assert "unexpected error" not in err and "RecursionError" not in err, err
    # the inputs replayed; the one recorded pose is no pose, so nothing could be checked
    assert code == 1, err
    assert "replayed" in err + out and "none could be checked" in err + out


def _rewrite(
    src: Path, dst: Path, shift_pose_x: float = 0.0, pose: bytes | None = None, **options: Any
) -> Path:
    """``src`` written again by the ``mcap`` library's own writer, with ``options`` (say, no
    channels repeated in the summary); with ``shift_pose_x``, the first recorded pose moved;
    with ``pose``, every recorded pose's payload replaced by it."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        writer = McapWriter(out, **options)
        writer.start("another writer", "")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        shifted = False
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            data = message.data
            if shift_pose_x and schema.name == "rlutf.PoseEstimate" and not shifted:
                moved = json.loads(data)
                moved["x"] += shift_pose_x
                data, shifted = json.dumps(moved).encode(), True
            if pose is not None and schema.name == "rlutf.PoseEstimate":
                data = pose
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        writer.finish()
    return dst


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A log with inputs and the poses computed from them, as the service writes it."""
    folder = tmp_path_factory.mktemp("recorded")
    inputs = write_log(folder / "in.mcap", simulated_inputs(seed=2, steps=6, beams=90))
    replay([inputs], folder / "recorded.mcap", foxglove=False)
    return folder / "recorded.mcap"


def test_a_log_whose_summary_lists_no_channels_is_read_and_audited(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The MCAP spec leaves repeating channels and schemas in the summary to the writer. A log
    written without them was called damaged by ``rlutf log info`` and ``log views`` (KeyError)
    and replayed as holding nothing: "no recorded poses in the input: nothing to audit", exit 0,
    whatever its poses were."""
    bare = {"repeat_channels": False, "repeat_schemas": False}
    log = _rewrite(recorded, tmp_path / "bare.mcap", **bare)
    with LogFile(recorded) as a, LogFile(log) as b:
        assert b.channels() == a.channels() and b.time_range == a.time_range
        assert list(b.messages()) == list(a.messages())
    assert main(["log", "info", str(log)]) == 0
    assert main(["log", "views", str(log), "--out", str(tmp_path / "views.mcap")]) == 0
    assert main(["replay", str(log), "--quiet", "--jobs", "1"]) == 0
    out, err = capsys.readouterr()
    assert "audit: passed" in out + err and "nothing to audit" not in out + err
    wrong = _rewrite(recorded, tmp_path / "wrong.mcap", shift_pose_x=1.0, **bare)
    assert main(["replay", str(wrong), "--quiet", "--jobs", "1"]) == 1
    # and without statistics either: read through
    nostats = _rewrite(recorded, tmp_path / "nostats.mcap", 1.0, use_statistics=False, **bare)
    assert main(["replay", str(nostats), "--quiet", "--jobs", "1"]) == 1
    # its channels listed but not their schemas: every channel was taken for one without a
    # schema, and the log for another tool's ("not an rlutf log", exit 2)
    noschemas = _rewrite(recorded, tmp_path / "noschemas.mcap", repeat_schemas=False)
    with LogFile(recorded) as a, LogFile(noschemas) as b:
        assert b.channels() == a.channels()
    assert main(["replay", str(noschemas), "--quiet", "--jobs", "1"]) == 0


@pytest.mark.parametrize(
    "options",
    [
        {"use_chunking": False},
        {"index_types": IndexType.NONE},
        {"index_types": IndexType.NONE, "use_statistics": False, "use_summary_offsets": False}
        | {"repeat_channels": False, "repeat_schemas": False},
    ],
    ids=["unchunked", "no chunk index", "no summary"],
)
def test_a_log_without_a_chunk_index_is_streamed_not_held_in_memory(
    options: dict[str, Any], tmp_path: Path
) -> None:
    """A log without chunk indexes (not chunked, or without a summary) was read by sorting all
    its messages in memory: a replay of a 70 MB unchunked log took 360 MB, and grew with the
    log. One in log-time order is now read as it lies, a message at a time."""
    path = tmp_path / "flat.mcap"
    payload = json.dumps({"pad": "x" * 2000}).encode()
    with open(path, "wb") as out:
        writer = McapWriter(out, chunk_size=200_000, **options)  # a chunk is read whole
        writer.start("another writer", "")
        schema = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
        channel = writer.register_channel("rlutf/robots/r1/events", "json", schema)
        for i in range(2000):  # 4 MB of payloads
            writer.add_message(channel, 1000 + i, payload, 1000 + i)
        writer.finish()
    with LogFile(path) as log:
        tracemalloc.start()
        try:
            seen = sum(1 for _ in log.messages())
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert seen == 2000
    assert peak < 2_000_000, f"{peak} bytes held to read 4 MB of messages"


def test_a_log_without_a_chunk_index_out_of_order_is_still_read_in_log_time_order(
    tmp_path: Path,
) -> None:
    path = tmp_path / "shuffled.mcap"
    with open(path, "wb") as out:
        writer = McapWriter(out, use_chunking=False)
        writer.start("another writer", "")
        schema = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
        channel = writer.register_channel("rlutf/robots/r1/events", "json", schema)
        for t in (5, 3, 9, 1, 3):
            writer.add_message(channel, t, str(t).encode(), t)
        writer.finish()
    with LogFile(path) as log:
        assert [r.log_time_ns for r in log.messages()] == [1, 3, 3, 5, 9]
        assert log.time_range == (1, 9)


@pytest.mark.parametrize("entry", ["dangling link", "folder", "fifo"])
def test_a_folders_log_entry_that_is_no_file_is_named_not_skipped(
    entry: str, recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder's ``run-2.mcap`` that is a symbolic link to a volume not mounted (or a folder, or
    a FIFO) was left out without a word: ``rlutf replay logs/`` said "audit: passed" over the
    logs it did read."""
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "run-1.mcap").write_bytes(recorded.read_bytes())
    odd = logs / "run-2.mcap"
    if entry == "dangling link":
        odd.symlink_to(tmp_path / "archive" / "run-2.mcap")
    elif entry == "folder":
        odd.mkdir()
    else:
        os.mkfifo(odd)
    for argv in (["replay", str(logs), "--quiet", "--jobs", "1"], ["log", "info", str(logs)]):
        assert main(argv) == 2
        out, err = capsys.readouterr()
        assert str(odd) in err and "audit: passed" not in out + err, err


def test_a_log_whose_every_recorded_pose_is_unreadable_fails_its_audit(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One unreadable pose among readable ones failed the audit, but a log whose every pose was
    overwritten said "no recorded poses in the input: nothing to audit", exit 0."""
    log = _rewrite(recorded, tmp_path / "overwritten.mcap", pose=b'{"x": "gone"}')
    for jobs in ("1", "2"):
        assert main(["replay", str(log), "--quiet", "--jobs", jobs]) == 1
        out, err = capsys.readouterr()
        assert "12 recorded poses are not valid PoseEstimates" in out + err
        assert "nothing to audit" not in out + err and "audit: FAILED" in out + err


def _reusing_an_id(path: Path, what: str, **options: Any) -> Path:
    """A file by the ``mcap`` library's writer whose ``what`` ("channel" or "schema") 1 is r1's
    events for the first message, and r2's odometry for the second: a writer that numbers them
    anew part way (as the library's does, by how many it has)."""
    with open(path, "wb") as out:
        writer = McapWriter(out, **options)
        writer.start("another writer", "")
        event = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
        first = writer.register_channel("rlutf/robots/r1/events", "json", event)
        writer.add_message(first, 1000, b'{"first": 1}', 1000)
        vars(writer)[f"_Writer__{what}s"].clear()
        odometry = writer.register_schema("rlutf.Odometry", "jsonschema", b"{}")
        again = writer.register_channel("rlutf/robots/r2/odom", "json", odometry)
        assert again == first if what == "channel" else odometry == event
        writer.add_message(again, 2000, b'{"second": 2}', 2000)
        writer.finish()
    return path


NO_SUMMARY: dict[str, Any] = {
    "index_types": IndexType.NONE,
    "use_statistics": False,
    "use_summary_offsets": False,
    "repeat_channels": False,
    "repeat_schemas": False,
}


@pytest.mark.parametrize("what", ["channel", "schema"])
@pytest.mark.parametrize(
    "options",
    [{}, NO_SUMMARY, {"use_chunking": False}],
    ids=["indexed", "no summary", "unchunked"],
)
def test_a_log_that_declares_an_id_twice_differently_is_refused(
    options: dict[str, Any], what: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A channel declared again under its id for another topic and schema was merged: indexed,
    both messages were read as r2's odometry (r1's event replayed as an Odometry); without a
    summary, the messages were read as declared, but ``rlutf log info`` counted both as r2's
    odometry. The MCAP format allows one definition per id, so which message is on which cannot
    be told: the file is refused, naming the id and both declarations."""
    path = _reusing_an_id(tmp_path / "reused.mcap", what, **options)
    with pytest.raises(RedeclaredLog) as refused, LogFile(path) as log:
        list(log.messages())
    said = str(refused.value)
    assert str(path) in said and f"{what} 1 is declared twice" in said, said
    if what == "channel":
        assert "rlutf/robots/r1/events" in said and "rlutf/robots/r2/odom" in said, said
    assert "rlutf.Event" in said and "rlutf.Odometry" in said, said
    for argv in (["log", "info", str(path)], ["replay", str(path), "--quiet", "--jobs", "1"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "declared twice" in err and "Traceback" not in err, err


@pytest.mark.parametrize("what", ["channel", "schema"])
@pytest.mark.parametrize(
    ("options", "cut"),
    [({}, False), (NO_SUMMARY, False), ({"use_chunking": False}, False), (NO_SUMMARY, True)],
    ids=["indexed", "no summary", "unchunked", "cut short"],
)
def test_recover_refuses_a_log_that_declares_an_id_twice_differently(
    options: dict[str, Any],
    cut: bool,
    what: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``rlutf log recover`` kept each id's first declaration and filed every later message under
    it: the file the readers refuse came out as a valid log, r2's odometry on r1's events topic
    (channel) or read as an rlutf.Event (schema). It is refused as the readers refuse it, nothing
    is written, and other files given with it are recovered all the same."""
    path = _reusing_an_id(tmp_path / "reused.mcap", what, **options)
    if cut:  # a crash's .part: its footer half-written
        whole = path.read_bytes()
        path = tmp_path / "reused.mcap.part"
        path.write_bytes(whole[:-20])
    with pytest.raises(RedeclaredLog) as refused:
        recover(path, tmp_path / "fixed.mcap")
    said = str(refused.value)
    assert str(path) in said and f"{what} 1 is declared twice" in said, said
    assert "rlutf.Event" in said and "rlutf.Odometry" in said, said
    assert not list(tmp_path.glob("fixed*")) and not list(tmp_path.glob(".fixed*"))
    other = write_log(tmp_path / "other.mcap", simulated_inputs(seed=1, steps=2, beams=30))
    out = tmp_path / "out"
    assert main(["log", "recover", str(path), str(other), str(out)]) == 2
    err = capsys.readouterr().err
    assert "declared twice" in err and str(path) in err and "Traceback" not in err, err
    assert sorted(p.name for p in out.iterdir()) == ["other.mcap"]
    with LogFile(out / "other.mcap") as log, LogFile(other) as original:
        assert list(log.messages()) == list(original.messages())


def test_logs_read_together_each_keep_their_own_channel_ids(tmp_path: Path) -> None:
    """Channel ids are a file's own: two logs that both number their first channel 1, for other
    topics, are read together with each message on its own file's topic."""
    paths = []
    for name, topic, t in (
        ("a", "rlutf/robots/r1/events", 1000),
        ("b", "rlutf/robots/r2/events", 1500),
    ):
        with open(tmp_path / f"{name}.mcap", "wb") as out:
            writer = McapWriter(out)
            writer.start("another writer", "")
            schema = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
            channel = writer.register_channel(topic, "json", schema)
            assert channel == 1
            for k in range(3):
                writer.add_message(channel, t + 1000 * k, json.dumps({"from": name}).encode(), t)
            writer.finish()
        paths.append(tmp_path / f"{name}.mcap")
    logs = [LogFile(p) for p in paths]
    try:
        read = [(r.topic, json.loads(r.payload)["from"]) for r in merged_messages(logs)]
    finally:
        for log in logs:
            log.close()
    a, b = ("rlutf/robots/r1/events", "a"), ("rlutf/robots/r2/events", "b")
    assert read == [a, b, a, b, a, b]


def test_messages_on_channels_without_a_schema_are_counted_not_given(tmp_path: Path) -> None:
    """What a channel without a schema holds cannot be told: a reader of some schemas does not
    get its messages, but counts them per topic (an audit says it could not read them)."""
    path = tmp_path / "bare.mcap"
    with open(path, "wb") as out:
        writer = McapWriter(out)
        writer.start("another writer", "")
        schema = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
        events = writer.register_channel("rlutf/robots/r1/events", "json", schema)
        bare = writer.register_channel("rlutf/robots/r2/scan", "json", 0)
        for t in range(5):
            writer.add_message(events if t % 2 else bare, t, b"{}", t)
        writer.finish()
    with LogFile(path) as log:
        assert log.read_counts() == ({}, set())  # nothing read yet
        assert [r.topic for r in log.messages({"rlutf.Event"})] == ["rlutf/robots/r1/events"] * 2
        counts = {("rlutf/robots/r1/events", "rlutf.Event"): 2, ("rlutf/robots/r2/scan", ""): 3}
        assert log.read_counts() == (counts, {"rlutf.Event", ""})
        assert [r.schema_name for r in log.messages()].count("") == 3
        assert log.read_counts() == (counts, None)
