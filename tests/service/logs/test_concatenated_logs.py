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
