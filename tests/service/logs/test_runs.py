"""Runs (WIRE.md v1.2, ``rlutf.run``): a folder of several runs is replayed, audited and
described run by run, never carrying a robot's state from one run into the next.

The runs are recorded by the service's own recorder (:class:`McapRecorder`, one per run as one
per start of the service) from the poses the engine computes for simulated inputs, one after
the other in one folder, as ``rlutf demo --seed K`` run several times leaves them: each run
puts its own building as version 1 of the same map id (the demo's store is temporary).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcaplog_fixtures import read_all, record_with_poses, simulated_inputs, write_log
from numpy.random import default_rng as rng

from rlutf.sim import make_building
from service.cli.main import main
from service.logs.audit import all_passed, audit
from service.logs.logtools import log_info, runs_info
from service.logs.mcapfile import LIBRARY, Record
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.logs.replay import REPLAY_INSTANCE, MixedRuns, replay
from service.logs.runs import LogRun, RunConflict, group_runs, run_outputs, run_tag

RUNS = 10
GAP_NS = 60_000_000_000  # the runs follow one another a minute apart


def record_run(
    folder: Path, tmp: Path, k: int, max_bytes: int = 1 << 28, tamper: bool = False
) -> McapRecorder:
    """Run ``k``: simulated inputs (seed ``k``) and the poses the engine computes for them,
    recorded as the live service records them (a pose at its scan's receive time)."""
    shift = k * GAP_NS
    inputs = [
        r._replace(log_time_ns=r.log_time_ns + shift)
        for r in simulated_inputs(seed=k, steps=12, beams=90, world=make_building(rng(100 + k)))
    ]

    def moved(robot: str, i: int, payload: bytes) -> bytes:
        if not tamper or i != 5:
            return payload
        data = json.loads(payload)
        data["x"] += 0.25
        return json.dumps(data).encode()

    scratch = tmp / f"inputs-{k}"
    scratch.mkdir(exist_ok=True)
    return record_with_poses(
        folder, scratch, inputs, moved, instance="demo", max_bytes=max_bytes, chunk_size=4096
    )


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[McapRecorder]]:
    """Ten runs in one folder; runs 2 and 7 rotated into several files."""
    tmp = tmp_path_factory.mktemp("runs")
    logs = tmp / "logs"
    recorders = [
        record_run(logs, tmp, k, max_bytes=15_000 if k in (2, 7) else 1 << 28) for k in range(RUNS)
    ]
    return logs, recorders


def logs_of(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.mcap"))


def test_each_run_names_itself_and_files_group_by_run(
    folder: tuple[Path, list[McapRecorder]],
) -> None:
    logs, recorders = folder
    assert len(recorders[2].files) >= 2 and len(recorders[0].files) == 1
    # a shell glob sorts the files by name; reversed, they must group the same
    runs = group_runs(list(reversed(logs_of(logs))))
    assert [r.run_id for r in runs] == [rec.run_id for rec in recorders]
    assert len({r.run_id for r in runs}) == RUNS
    for run, rec in zip(runs, recorders, strict=True):
        assert list(run.files) == rec.files
        assert [t.sequence for t in run.tags if t is not None] == list(range(len(rec.files)))
        assert run.instance == "demo" and run.missing == []
    # the files of one run without its first: reported as missing, not an error
    assert group_runs(recorders[2].files[1:])[0].missing == [0]


def test_replay_of_a_folder_audits_ten_passing_runs(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs, recorders = folder
    out = tmp_path / "replayed"
    assert main(["replay", *map(str, logs_of(logs)), "--out", f"{out}/", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"audit: passed ({RUNS} runs)" in text and "FAILED" not in text
    assert text.count("recorded vs recomputed poses") == RUNS
    outputs = sorted(out.glob("*.replay.mcap"))
    assert len(outputs) == RUNS
    for path in outputs:
        with LogFile(path) as lf:
            tag = run_tag(lf)
        assert tag is not None and tag.instance == REPLAY_INSTANCE and tag.sequence == 0
        assert dict(tag.extra)["replayed_run"] in {r.run_id for r in recorders}
    # a replay's outputs are runs of their own: auditing them again passes, run by run
    again = tmp_path / "again.mcap"
    assert main(["replay", *map(str, outputs), "--out", str(again), "--quiet"]) == 0
    assert sorted(tmp_path.glob("again-run*.mcap")) == [
        tmp_path / f"again-run{k}.mcap" for k in sorted(range(1, RUNS + 1), key=str)
    ]


def test_an_audit_with_no_out_keeps_nothing_and_says_so(
    folder: tuple[Path, list[McapRecorder]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # An auditor's first command: `rlutf replay logs/` (it said "--out is required").
    logs, _ = folder
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where the scratch logs go
    monkeypatch.chdir(tmp_path)
    before = sorted(tmp_path.rglob("*"))
    assert main(["replay", str(logs), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"audit: passed ({RUNS} runs)" in text and "FAILED" not in text
    assert text.count("-> not kept (--out keeps them)") == RUNS
    assert sorted(tmp_path.rglob("*")) == before  # nothing written, nothing left aside


def test_merging_two_runs_is_refused(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path
) -> None:
    _, recorders = folder
    runs = [recorders[0].files[0], recorders[1].files[0]]
    with pytest.raises(MixedRuns, match="2 runs"):
        replay(runs)
    # why: the same messages in files that do not name their run are one run, and replayed
    # as one the second run is localized on the first run's map (a false tamper alarm)
    merged = [write_log(tmp_path / f"{k}.mcap", read_all(p)) for k, p in enumerate(runs)]
    result = replay(merged)
    assert not all_passed(audit(result.recorded, result.recomputed), 1e-9, 1e-9)


def test_a_tampered_run_fails_alone(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs, _ = folder
    mixed = tmp_path / "logs"
    shutil.copytree(logs, mixed)
    bad = record_run(mixed, tmp_path, RUNS, tamper=True)
    code = main(["replay", *map(str, logs_of(mixed)), "--out", str(tmp_path / "x.mcap"), "--quiet"])
    assert code == 1
    text = capsys.readouterr().out
    assert f"FAILED (1 of {RUNS + 1} runs)" in text
    # the summary's last row is the tampered run (the latest started), and only it failed
    failed = [line.split("│") for line in text.splitlines() if "FAILED │" in line]
    assert len(failed) == 1 and failed[0][1].strip() == str(RUNS + 1)
    assert bad.run_id[:8] in failed[0][3]
    assert f"run {RUNS + 1} of {RUNS + 1}: {bad.run_id}" in text
    assert "written by" not in text  # the same version: nothing excuses the difference


def test_a_log_of_another_version_that_fails_says_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A log written by another version of rlutf (its MCAP header's library), whose poses do not
    # reproduce here: the audit fails, and says which version to audit it with.
    monkeypatch.setattr("service.logs.mcapfile.LIBRARY", "rlutf 0.0.1")
    old = record_run(tmp_path / "logs", tmp_path, 0, tamper=True)
    monkeypatch.undo()
    with open(old.files[0], "rb") as f:
        assert make_reader(f).get_header().library == "rlutf 0.0.1"
    code = main(["replay", str(old.files[0]), "--out", str(tmp_path / "x.mcap"), "--quiet"])
    assert code == 1
    text = " ".join(capsys.readouterr().out.split())
    assert "audit: FAILED" in text
    assert "written by rlutf 0.0.1" in text and "pip install 'rlutf==0.0.1'" in text
    # log info names the writer before any audit
    assert main(["log", "info", str(old.files[0]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["writer"] == "rlutf 0.0.1"
    assert main(["log", "info", str(old.files[0])]) == 0
    assert "written by: rlutf 0.0.1" in capsys.readouterr().out


def test_log_info_describes_each_run(
    folder: tuple[Path, list[McapRecorder]], capsys: pytest.CaptureFixture[str]
) -> None:
    logs, recorders = folder
    assert main(["log", "info", *map(str, logs_of(logs)), "--json"]) == 0
    runs = json.loads(capsys.readouterr().out)["runs"]
    assert [r["run_id"] for r in runs] == [rec.run_id for rec in recorders]
    for run, rec in zip(runs, recorders, strict=True):
        assert [f["path"] for f in run["files"]] == [str(p) for p in rec.files]
        assert run["robots"]["r1"]["scan"] == 12 and run["robots"]["r1"]["pose"] == 12
        assert run["maps"] == {"m1": [1]}
    assert main(["log", "info", *map(str, logs_of(logs))]) == 0
    text = capsys.readouterr().out
    assert text.count("files of run") == RUNS and f"run {RUNS} of {RUNS}" in text
    assert text.count(f"written by: {LIBRARY}") == RUNS


def test_rotated_files_carry_maps_outside_their_own_time(
    folder: tuple[Path, list[McapRecorder]],
) -> None:
    _, recorders = folder
    files = recorders[2].files
    infos = [log_info(p) for p in files]
    assert infos[0].carried_maps == 0 and all(i.carried_maps == 1 for i in infos[1:])
    runs = [(i.run or {}).get("run_id") for i in infos]
    assert runs == [recorders[2].run_id] * len(files)
    assert [(i.run or {}).get("sequence") for i in infos] == [str(n) for n in range(len(files))]
    # each file's time starts at its own first message, not at the carried map's log_time
    spans = [i.time_range for i in infos]
    assert all(s is not None for s in spans)
    for before, after in itertools.pairwise(spans):
        assert before is not None and after is not None and before[1] <= after[0]
    with LogFile(files[1]) as lf:
        first_map = next(iter(lf.messages({"rlutf.Map"})))
        assert lf.time_range is not None and lf.time_range[0] == first_map.log_time_ns
    (run,) = runs_info(files)
    assert run.time_range == (spans[0][0], spans[-1][1])  # type: ignore[index]


def test_files_without_run_metadata_form_one_run(tmp_path: Path) -> None:
    records = simulated_inputs(steps=6)
    half = len(records) // 2
    parts = [
        write_log(tmp_path / "b.mcap", records[half:]),
        write_log(tmp_path / "a.mcap", records[:half]),
    ]
    (run,) = group_runs(parts)
    assert run.run_id is None and list(run.files) == parts
    assert run.label == "files without rlutf.run"
    assert len(replay(parts).recomputed["r1"]) == 6


def test_the_same_file_twice_counts_once_and_a_copy_is_a_conflict(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path
) -> None:
    _, recorders = folder
    first = recorders[0].files[0]
    assert len(group_runs([first, first])[0].files) == 1
    copy = tmp_path / "copy.mcap"
    shutil.copy(first, copy)
    with pytest.raises(RunConflict, match="both file 0 of run"):
        group_runs([first, copy])


def test_recover_several_files_lists_them_by_run(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, recorders = folder
    files = recorders[7].files
    broken = []
    for path in files:
        cut = tmp_path / (path.name + ".part")
        cut.write_bytes(path.read_bytes()[: path.stat().st_size * 3 // 4])
        broken.append(cut)
    assert main(["log", "recover", *map(str, broken), str(tmp_path / "fixed")]) == 0
    text = capsys.readouterr().out
    fixed = [tmp_path / "fixed" / p.name for p in files]
    assert all(p.exists() for p in fixed)
    assert f"run 1: {recorders[7].run_id}" in text
    (run,) = group_runs(fixed)
    assert run.run_id == recorders[7].run_id and list(run.files) == fixed


@pytest.mark.parametrize(
    ("out", "names"),
    [
        ("x.mcap", ["x-run1.mcap", "x-run2.mcap"]),
        ("dir/", ["dir/a.replay.mcap", "dir/a-2.replay.mcap"]),
    ],
)
def test_outputs_of_several_runs(out: str, names: Sequence[str]) -> None:
    runs = [LogRun((Path("logs/a.mcap"),), (None,), 0), LogRun((Path("old/a.mcap"),), (None,), 1)]
    assert run_outputs(out, runs) == [Path(n) for n in names]
    assert run_outputs("x.mcap", runs[:1]) == [Path("x.mcap")]


def test_plots_of_several_runs_go_to_a_folder_per_run(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, recorders = folder
    files = [str(p) for rec in recorders[:2] for p in rec.files]
    plots = tmp_path / "plots"
    argv = ["replay", *files, "--out", str(tmp_path / "x.mcap"), "--plot", str(plots), "--quiet"]
    assert main(argv) == 0
    capsys.readouterr()
    for k in (1, 2):
        for robot in ("r1", "r2"):
            assert (plots / f"run{k}" / f"{robot}.png").read_bytes()[:4] == b"\x89PNG"


def test_a_run_without_poses_is_named_but_fails_nothing(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, recorders = folder
    inputs_only = write_log(tmp_path / "other-tool.mcap", simulated_inputs(steps=3))
    files = [str(recorders[0].files[0]), str(inputs_only)]
    assert main(["replay", *files, "--out", f"{tmp_path}/", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "nothing to audit" in text and "audit: passed (1 run; 1 with nothing to audit)" in text
    assert (tmp_path / "other-tool.replay.mcap").exists()


def test_an_unreadable_file_or_run_is_named_and_the_others_audited(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, recorders = folder
    garbage = tmp_path / "notes.mcap"
    garbage.write_text("not a log")
    damaged = tmp_path / "damaged.mcap"
    source = recorders[1].files[0]
    data = bytearray(source.read_bytes())
    with source.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    for index in summary.chunk_indexes:  # inside every chunk: their CRCs no longer match
        middle = index.chunk_start_offset + index.chunk_length // 2
        data[middle : middle + 64] = bytes(64)
    damaged.write_bytes(bytes(data))
    files = [str(recorders[0].files[0]), str(garbage), str(damaged)]
    assert main(["replay", *files, "--out", f"{tmp_path}/out/", "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "notes.mcap: not an MCAP file" in captured.err
    assert "damaged.mcap" in captured.err and "rlutf log recover" in captured.err
    assert "1 run(s) and 1 file(s) could not be read; 1 run(s) passed" in captured.out
    # an audit that fails still says so first: exit 1, not 2
    bad = record_run(tmp_path / "tampered", tmp_path, RUNS + 1, tamper=True)
    files = [*map(str, bad.files), str(garbage)]
    assert main(["replay", *files, "--out", f"{tmp_path}/out2/", "--quiet"]) == 1


def test_log_info_names_an_unreadable_file_and_describes_the_others(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, recorders = folder
    garbage = tmp_path / "notes.mcap"
    garbage.write_text("not a log")
    files = [*map(str, recorders[2].files), str(garbage)]
    assert main(["log", "info", *files, "--json"]) == 2
    captured = capsys.readouterr()
    data = json.loads(captured.out)
    assert [r["run_id"] for r in data["runs"]] == [recorders[2].run_id]
    assert [u["path"] for u in data["unreadable"]] == [str(garbage)]
    assert "notes.mcap: not an MCAP file" in captured.err


def test_a_log_folder_is_given_as_it_is(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``rlutf replay logs/`` (and every ``rlutf log`` command) takes the folder's ``*.mcap``
    files, as the shell's ``logs/*.mcap`` gives them."""
    logs, recorders = folder
    assert main(["replay", str(logs), "--out", f"{tmp_path}/out/", "--quiet"]) == 0
    assert f"audit: passed ({RUNS} runs)" in capsys.readouterr().out
    assert len(list((tmp_path / "out").glob("*.replay.mcap"))) == RUNS
    assert main(["log", "info", str(logs), "--json"]) == 0
    by_folder = json.loads(capsys.readouterr().out)
    assert main(["log", "info", *map(str, logs_of(logs)), "--json"]) == 0
    assert by_folder == json.loads(capsys.readouterr().out)
    assert [r["run_id"] for r in by_folder["runs"]] == [rec.run_id for rec in recorders]
    # a folder of one log: that log, described as one file
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(recorders[0].files[0], one)
    assert main(["log", "views", str(one), "--out", str(tmp_path / "views")]) == 0
    assert (tmp_path / "views" / recorders[0].files[0].name).is_file()
    capsys.readouterr()
    # the unfinished logs a crash leaves: recovered from the folder, named when none is finished
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    for path in recorders[7].files:
        (crashed / (path.name + ".part")).write_bytes(path.read_bytes()[:-200])
    assert main(["replay", str(crashed), "--out", f"{tmp_path}/x/"]) == 2
    err = capsys.readouterr().err
    assert "a folder with no log file (*.mcap) in it" in err
    assert f"{len(recorders[7].files)} unfinished log(s)" in err and "rlutf log recover" in err
    assert main(["log", "recover", str(crashed), str(tmp_path / "fixed")]) == 0
    (run,) = group_runs(logs_of(tmp_path / "fixed"))
    assert run.run_id == recorders[7].run_id and len(run.files) == len(recorders[7].files)
    capsys.readouterr()
    # the other way round: recover on a folder of finished logs says there is nothing to do
    assert main(["log", "recover", str(logs), str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "a folder with no log file (*.mcap.part) in it" in err
    assert f"{len(logs_of(logs))} complete log(s) (.mcap): nothing to recover" in err


def test_an_audit_of_a_folder_names_its_unfinished_logs(
    folder: tuple[Path, list[McapRecorder]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder after a crash and a restart holds finished logs and the ``.part`` the crash
    left: the audit of the folder must not pass as if it had read everything (it says
    ``incomplete``, exit 2, and how to recover the file); once the copy recovered from it is
    given too, the audit is whole. A ``.part`` being recorded now is named, not a fault."""
    _, recorders = folder
    logs = tmp_path / "logs"
    logs.mkdir()
    shutil.copy(recorders[0].files[0], logs)
    (part,) = [logs / (p.name + ".part") for p in recorders[1].files[:1]]
    part.write_bytes(recorders[1].files[0].read_bytes()[:-200])
    old = time.time() - 3600  # last written an hour ago: its recorder is gone
    os.utime(part, (old, old))
    assert main(["replay", str(logs), "--quiet"]) == 2
    out, err = capsys.readouterr()
    assert "audit: incomplete" in out and "1 file(s) could not be read; 1 run(s) passed" in out
    assert f"not audited: {part}: this log was left unfinished" in err
    assert f"rlutf log recover {logs}/ RECOVERED/" in err
    # The shell's logs/*.mcap is the folder: the same verdict (it passed, the .part unnamed).
    assert main(["replay", *map(str, logs.glob("*.mcap")), "--quiet"]) == 2
    out, err = capsys.readouterr()
    assert "audit: incomplete" in out and f"not audited: {part}: this log was left" in err
    assert main(["log", "info", str(logs)]) == 0
    assert f"not described: {part}" in capsys.readouterr().err
    assert main(["log", "views", str(logs), "--out", f"{tmp_path}/views/"]) == 0
    assert f"not copied: {part}" in capsys.readouterr().err
    fixed = tmp_path / "fixed"
    assert main(["log", "recover", str(logs), str(fixed)]) == 0
    capsys.readouterr()
    assert main(["replay", str(logs), str(fixed), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "audit: passed (2 runs)" in out and "not audited" not in err
    globs = [*map(str, logs.glob("*.mcap")), *map(str, fixed.glob("*.mcap"))]
    assert main(["replay", *globs, "--quiet"]) == 0
    assert "not audited" not in capsys.readouterr().err
    os.utime(part)  # written just now: being recorded
    (fixed / part.name.removesuffix(".part")).unlink()
    assert main(["replay", str(logs), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "audit: passed (1 run; 1 log(s) being recorded, not audited)" in out
    assert f"not audited: {part}: this log is being recorded now" in err


@pytest.mark.parametrize("code", ["recording_resumed", "recorder_overflow"])
def test_an_audit_stops_at_a_recording_gap_and_says_so(
    code: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log with a recording gap (the recorder could not write, or its queue was full: the
    gap's inputs are not in it, ``recording_resumed`` or ``recorder_overflow`` says when it
    began) audits every pose before the gap and names those after it, not audited; without that
    Event the same log fails (a false alarm; an overflow's Event was stamped when it was written,
    after the gap, and such a log failed too)."""
    from schemas import Event, encode

    inputs = simulated_inputs(seed=4, steps=30, beams=90)
    computed = replay([write_log(tmp_path / "all.mcap", inputs)])
    scans = sorted(r.log_time_ns for r in inputs if r.schema_name == "rlutf.LaserScan")
    began, resumed = scans[len(scans) // 2], scans[len(scans) // 2 + 8]  # 4 steps of 2 robots
    received = {
        (r.topic.split("/")[2], r.publish_time_ns): r.log_time_ns
        for r in inputs
        if r.schema_name == "rlutf.LaserScan"
    }
    poses = [
        Record(f"rlutf/robots/{robot}/pose", "rlutf.PoseEstimate", p.payload, at, p.stamp_ns)
        for robot, records in computed.recomputed.items()
        for p in records
        if not began <= (at := received[(robot, p.stamp_ns)]) < resumed  # lost in the gap
    ]
    kept = [r for r in inputs if not began <= r.log_time_ns < resumed]
    stamp = min(s for (_, s), at in received.items() if at >= began)  # the gap's first scan
    event = Event(
        stamp_ns=stamp,
        level="warning",
        code=code,
        key="rlutf/service/demo",
        message="recording resumed after 0.4 s: 24 messages were not logged",
    )
    note = Record("rlutf/events", "rlutf.Event", encode(event), resumed, stamp)
    rows = sorted([*kept, *poses], key=lambda r: r.log_time_ns)
    with_gap = write_log(tmp_path / "gap.mcap", sorted([*rows, note], key=lambda r: r.log_time_ns))
    assert main(["replay", str(with_gap), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "recorded poses after a recording gap" in out and "not audited" in out
    assert "audit: passed" in out
    silent = write_log(tmp_path / "silent.mcap", rows)  # the same gap, no Event
    assert main(["replay", str(silent), "--quiet"]) == 1
