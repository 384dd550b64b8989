"""A log file with another one appended (`cat a.mcap b.mcap > c.mcap`) is refused, not audited.

The summary was read from where the last footer says it starts to the first footer met, so a
complete log followed by a copy of itself read as the first copy alone: `rlutf replay` said
"audit: passed" and `rlutf log info` listed it, with the whole second half of the file never
read. A footer anywhere but at the end of the file now makes the file unreadable (exit 2),
named as files put together.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from mcaplog_fixtures import record_with_poses, simulated_inputs

from service.cli.main import main
from service.logs.mcaprecords import RecordError, read_summary
from service.logs.salvage import recover


@pytest.fixture
def doubled(tmp_path: Path) -> Path:
    rec = record_with_poses(tmp_path / "logs", tmp_path, simulated_inputs(steps=5, beams=90))
    (log,) = rec.files
    data = log.read_bytes()
    out = tmp_path / "doubled"
    out.mkdir()
    (out / log.name).write_bytes(data + data)
    return out / log.name


def test_a_log_followed_by_another_is_not_read_as_the_first_alone(doubled: Path) -> None:
    with open(doubled, "rb") as f, pytest.raises(RecordError, match="concatenated"):
        read_summary(f)


def test_replay_and_log_info_refuse_a_doubled_log(
    doubled: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(doubled.parent), "--quiet"]) == 2
    assert main(["log", "info", str(doubled)]) != 0
    out, err = capsys.readouterr()
    assert "audit: passed" not in out + err
    assert "concatenated" in err and "Traceback" not in err, err


def test_log_recover_does_not_call_a_doubled_log_read_to_its_end(
    doubled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`rlutf log recover`, which the refusal suggests, copied the first file and said "the
    input was read to its end, nothing was missing", the second never read."""
    size = doubled.stat().st_size
    report = recover(doubled, tmp_path / "fixed.mcap")
    assert not report.complete
    assert report.stopped_at == size // 2 and "after its footer" in str(report.stopped)
    assert main(["log", "recover", str(doubled), str(tmp_path / "fixed2.mcap")]) == 0
    out = capsys.readouterr().out
    assert "nothing was missing" not in out and "after its footer" in out, out


def test_two_different_logs_put_together_are_named_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cat p1.mcap p0.mcap`: the summary offset of the second file points into it, and reading
    on from the first file's end met the second's magic as a record "4.8e18 bytes long"."""
    a = record_with_poses(tmp_path / "a", tmp_path, simulated_inputs(steps=5, beams=90))
    b = record_with_poses(tmp_path / "b", tmp_path, simulated_inputs(steps=8, beams=90))
    out = tmp_path / "both"
    out.mkdir()
    (out / "both.mcap").write_bytes(a.files[0].read_bytes() + b.files[0].read_bytes())
    assert main(["replay", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "concatenated" in err and "bytes long" not in err, err
