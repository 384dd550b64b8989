"""``rlutf log info``, ``rlutf log recover`` and how damaged files are reported."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcaplog_fixtures import read_all, simulated_inputs

from service.cli.main import main
from service.logs.logtools import log_info
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import DamagedLog, LogFile, NotALog
from service.logs.replay import replay
from service.logs.salvage import recover

CONFIG = {"prefix": "rlutf", "instance": "edge-1", "workers": 0}


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded log with many small chunks and poses (from a replay of simulated inputs)."""
    folder = tmp_path_factory.mktemp("logs")
    src = folder / "inputs.mcap"
    rec = McapRecorder(folder / "rec", chunk_size=2048, foxglove=True)
    rec.set_config(CONFIG)
    for r in simulated_inputs(steps=12):
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    rec.close()
    (path,) = rec.files
    # Add recomputed poses, so the file looks like a service log with outputs.
    replay([path], src, foxglove=True, chunk_size=4096)
    return src


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_info_lists_channels_robots_maps(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = log_info(log)
    topics = {c.topic: c for c in info.channels}
    assert topics["rlutf/robots/r1/scan"].messages == 12
    assert topics["rlutf/robots/r1/scan"].schema_name == "rlutf.LaserScan"
    assert topics["rlutf/robots/r2/pose"].messages == 12
    assert set(info.robots) == {"r1", "r2"} and info.robots["r1"]["odom"] == 13
    assert info.maps == {"m1": [1]}
    assert info.time_range is not None and info.time_range[0] < info.time_range[1]
    code, out, _ = _run(["log", "info", str(log)], capsys)
    assert code == 0
    for text in ("rlutf/robots/r2/scan", "rlutf.PoseEstimate", "map m1", "instance"):
        assert text in out
    code, out, _ = _run(["log", "info", str(log), "--json"], capsys)
    data = json.loads(out)
    assert code == 0 and data["messages"] == info.messages and data["maps"] == {"m1": [1]}


def test_not_mcap_and_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world, not a log at all")
    for argv in (
        ["log", "info", str(junk)],
        ["replay", str(junk), "--out", str(tmp_path / "o")],
        ["log", "recover", str(junk), str(tmp_path / "r.mcap")],
        ["log", "info", str(tmp_path / "missing.mcap")],
    ):
        code, _, err = _run(argv, capsys)
        assert code == 2 and "Traceback" not in err
        assert "not an MCAP file" in err or "cannot open" in err
    with pytest.raises(NotALog):
        LogFile(junk)


def test_truncated_files_get_a_recover_hint_and_recover_keeps_complete_chunks(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = log.read_bytes()
    original = read_all(log)
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 20
    cuts = sorted({*range(8, len(data), max(len(data) // 37, 1)), len(data) - 1, len(data) - 9})
    recovered_counts = []
    for k, cut in enumerate(cuts):
        broken = tmp_path / f"cut{cut}.mcap"
        broken.write_bytes(data[:cut])
        with pytest.raises(DamagedLog, match="rlutf log recover"):
            LogFile(broken)
        if k % 6 == 0:
            for argv in (
                ["log", "info", str(broken)],
                ["replay", str(broken), "--out", str(tmp_path / "o.mcap"), "--quiet"],
            ):
                code, _, err = _run(argv, capsys)
                assert code == 2 and "rlutf log recover" in err and "Traceback" not in err
        fixed = tmp_path / f"fixed{cut}.mcap"
        report = recover(broken, fixed)
        assert report.stopped is not None and report.bad_chunks == 0
        got = read_all(fixed)
        # every complete chunk and nothing else: the messages are a prefix of the original
        assert got == original[: len(got)]
        assert report.messages == len(got)
        recovered_counts.append(len(got))
        if got and k % 6 == 0:
            with LogFile(fixed) as lf:
                assert lf.config() == replay([log]).config.settings
            assert replay([fixed]).config.prefix == "rlutf"
    assert recovered_counts == sorted(recovered_counts)
    assert recovered_counts[0] == 0 and recovered_counts[-1] > 0.9 * len(original)
    # an intact file: everything, complete
    report = recover(log, tmp_path / "same.mcap")
    assert report.complete and read_all(tmp_path / "same.mcap") == original


def test_corrupt_chunk_is_reported_and_skipped_by_recover(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    data = bytearray(log.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    code, _, err = _run(["log", "info", str(bad)], capsys)
    assert code == 2 and "rlutf log recover" in err and "Traceback" not in err
    code, _, err = _run(["replay", str(bad), "--out", str(tmp_path / "o.mcap"), "--quiet"], capsys)
    assert code == 2 and "rlutf log recover" in err and "Traceback" not in err
    assert not (tmp_path / "o.mcap").exists() and not (tmp_path / "o.mcap.part").exists()
    code, out, err = _run(["log", "recover", str(bad), str(tmp_path / "fixed.mcap")], capsys)
    assert code == 0 and "skipped 1 damaged chunk(s)" in err
    assert "read to its end" in out and "nothing was missing" not in out
    original = read_all(log)
    got = read_all(tmp_path / "fixed.mcap")
    assert 0 < len(original) - len(got) < len(original) // 10
    assert set(got) <= set(original)


def test_recover_refuses_to_overwrite_its_input(
    log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = _run(["log", "recover", str(log), str(log)], capsys)
    assert code == 2 and "must not be the input" in err


@pytest.mark.parametrize("into_folder", [False, True])
def test_recover_of_x_part_into_x_keeps_its_input(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], into_folder: bool
) -> None:
    """``rlutf log recover X.mcap.part X.mcap`` (or a folder of .part files into itself)
    wrote its output first as ``X.mcap.part``: it truncated its input, recovered nothing of it
    ("no message could be recovered (the input is cut at byte 3063)") and deleted it."""
    data = log.read_bytes()
    cut = data[: len(data) * 3 // 4]  # a recording cut short: a .part file
    folder = tmp_path / "logs"
    folder.mkdir()
    part = folder / "run-001.mcap.part"
    part.write_bytes(cut)
    out = folder if into_folder else folder / "run-001.mcap"
    code, stdout, err = _run(["log", "recover", str(part), str(out)], capsys)
    assert code == 0 and "recovered" in stdout, err
    assert part.read_bytes() == cut  # the input untouched
    got = read_all(folder / "run-001.mcap")
    assert len(got) > 0 and got == read_all(log)[: len(got)]
    assert sorted(p.name for p in folder.iterdir()) == ["run-001.mcap", "run-001.mcap.part"]


def test_recover_with_nothing_to_salvage_or_nowhere_to_write_says_so(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # "recovered 0 messages", exit 0 and an empty log left to be taken for a recovered run
    tiny = tmp_path / "tiny.mcap.part"
    tiny.write_bytes(log.read_bytes()[:8])
    code, out, err = _run(["log", "recover", str(tiny), str(tmp_path / "t.mcap")], capsys)
    assert code == 2 and "no message could be recovered" in err and not out
    assert not (tmp_path / "t.mcap").exists()
    # an output in a folder that does not exist is refused before any reading, with the fix
    code, _, err = _run(["log", "recover", str(log), str(tmp_path / "no" / "r.mcap")], capsys)
    assert code == 2 and "does not exist; create it" in err


def _middle_chunk(log: Path) -> tuple[int, int]:
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 4
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    return chunk.chunk_start_offset, chunk.chunk_length


@pytest.mark.parametrize("wrong", [1, 1000, 2**40])
def test_recover_salvages_every_intact_chunk_past_a_corrupted_chunk_length(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], wrong: int
) -> None:
    # Issue 19: one corrupted chunk length made recover keep only the first half of the file.
    start, _ = _middle_chunk(log)
    data = bytearray(log.read_bytes())
    field = slice(start + 1, start + 9)
    data[field] = (int.from_bytes(data[field], "little") + wrong).to_bytes(8, "little")
    bad = tmp_path / "badlength.mcap"
    bad.write_bytes(bytes(data))
    code, _, err = _run(["log", "recover", str(bad), str(tmp_path / "fixed.mcap")], capsys)
    assert code == 0 and "unreadable stretch" in err, err
    original = read_all(log)
    got = read_all(tmp_path / "fixed.mcap")
    assert set(got) <= set(original)
    lost = len(original) - len(got)
    assert 0 <= lost < len(original) // 10, "at most the damaged chunk is lost"
    assert got[-1] == original[-1], "the chunks after the damage are salvaged"
    with LogFile(tmp_path / "fixed.mcap") as lf:
        assert lf.config() == replay([log]).config.settings


def test_recover_drops_a_duplicated_chunk(log: Path, tmp_path: Path) -> None:
    start, length = _middle_chunk(log)
    data = log.read_bytes()
    doubled = tmp_path / "doubled.mcap"
    doubled.write_bytes(
        data[: start + length] + data[start : start + length] + data[start + length :]
    )
    report = recover(doubled, tmp_path / "fixed.mcap")
    assert report.duplicate_chunks == 1 and report.bad_chunks == 0
    assert read_all(tmp_path / "fixed.mcap") == read_all(log)


def test_a_config_record_that_is_not_json_stops_replay_unless_settings_are_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    from mcap.writer import Writer

    from service.logs.mcapread import UnreadableConfig

    bad = tmp_path / "badconfig.mcap"
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("rlutf.config", {"json": "{prefix: rlutf"})
        w.finish()
    with pytest.raises(UnreadableConfig, match="not a JSON object"):
        replay([bad])
    code, _, err = _run(["replay", str(bad), "--out", str(tmp_path / "o.mcap"), "--quiet"], capsys)
    assert code == 2 and "rlutf.config" in err and "--settings" in err and "Traceback" not in err
    result = replay([bad], assignments=["prefix=rlutf"])
    assert result.config.prefix == "rlutf"
    assert any("rlutf.config" in r.getMessage() for r in caplog.records)


def test_a_log_being_recorded_says_so_and_how_to_read_it_now(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = McapRecorder(tmp_path / "rec", chunk_size=2048, flush_interval_s=0.05)
    rec.set_config(CONFIG)
    inputs = simulated_inputs(steps=12)
    try:
        for r in inputs:
            rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
        (part,) = _wait_for_part(tmp_path / "rec", rec)
        code, _, err = _run(["log", "info", str(part)], capsys)
        assert code == 2 and "Traceback" not in err
        assert "is being recorded now" in err and "incomplete or damaged" not in err
        assert f"rlutf log recover {part} COPY.mcap" in err
        # what it says works while the recorder still writes: a copy of the complete chunks
        copy = tmp_path / "copy.mcap"
        code, _, _ = _run(["log", "recover", str(part), str(copy)], capsys)
        assert code == 0 and part.exists()
        code, out, _ = _run(["log", "info", str(copy)], capsys)
        assert code == 0 and "rlutf.LaserScan" in out
        copied = [r.payload for r in read_all(copy) if r.schema_name.startswith("rlutf.")]
        assert copied and copied == [r.payload for r in inputs][: len(copied)]
    finally:
        rec.close()
    # an unfinished file nobody writes any more (a crash) is told apart by its age
    left = tmp_path / "left.mcap.part"
    left.write_bytes(part.with_suffix("").read_bytes()[:-100])  # the finished file, cut short
    old = left.stat().st_mtime - 3600
    os.utime(left, (old, old))
    code, _, err = _run(["log", "info", str(left)], capsys)
    assert code == 2 and "was left unfinished" in err and "rlutf log recover" in err


def _wait_for_part(folder: Path, rec: McapRecorder, timeout: float = 10.0) -> list[Path]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        parts = list(folder.glob("*.mcap.part"))
        if parts and rec.queued == 0 and parts[0].stat().st_size > 10_000:
            time.sleep(0.2)  # a flush after the last message
            return parts
        time.sleep(0.05)
    raise AssertionError(f"no .mcap.part in {folder}")


@pytest.mark.parametrize("started", [None, "17x"])
def test_info_says_a_damaged_run_record_is_damaged(
    log: Path, started: str | None, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flipped byte in the key ``started_ns`` of ``rlutf.run`` showed "started 1970-01-01"."""
    from dataclasses import replace

    from rich.console import Console

    from service.logs.logtools import render_info

    info = log_info(log)
    run = {"run_id": "r", "instance": "edge-1", "sequence": "0"}
    if started is not None:
        run["started_ns"] = started
    render_info(replace(info, run=run), Console(width=200))
    out = capsys.readouterr().out
    assert "1970" not in out and "started unknown" in out and "damaged" in out, out
