"""A log from elsewhere may hold anything: the log tools read it to the end, whatever its
payloads hold. A payload nested past the JSON parser's depth (100,000 brackets, a few hundred
kilobytes) in an Event, a Map or a pose crashed ``rlutf log info``, ``rlutf replay`` and
``rlutf log views`` with an "unexpected error" (a RecursionError, to be reported as a bug)."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs, write_log

from service.cli.main import main
from service.logs.mcapfile import Record

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
    assert code == 0, err  # the pose is no pose: nothing to audit, the inputs replayed
    assert "replayed" in err + out
