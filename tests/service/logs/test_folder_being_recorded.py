"""A log folder whose only logs are unfinished: the refusal says how many of them a running
service is recording now, so that an operator who runs ``rlutf log info logs/`` beside a live
``rlutf serve`` (the README's step 6) is not told, as after a crash, only to recover them.

Found by the outsider review: with ``rlutf serve`` recording and a simulated fleet driving,
``rlutf log info logs/`` said "it holds 1 unfinished log(s) (.mcap.part): copy what they hold
with rlutf log recover" and nothing of the log being recorded at that moment."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs

from service.cli.main import main
from service.logs.mcaplog import McapRecorder
from service.logs.partfile import RECENT_S


def _written(rec: McapRecorder, timeout: float = 20.0) -> Path:
    """The recorder's ``.part`` once it holds something."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        part = rec.current_path
        if part is not None and part.is_file() and part.stat().st_size > 0:
            return part
        time.sleep(0.05)
    raise AssertionError("the recorder wrote no .part file")


def test_a_folder_being_recorded_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    rec = McapRecorder(logs, flush_interval_s=0.1)
    try:
        rec.set_config({"prefix": "rlutf"})
        for r in simulated_inputs(seed=1, steps=5, beams=90):
            rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
        part = _written(rec)
        assert main(["log", "info", str(logs)]) == 2
        err = capsys.readouterr().err
        assert "1 unfinished log(s) (.mcap.part), 1 of them being recorded now" in err
        assert f"rlutf log recover {logs}/ FOLDER" in err
        # not written for a minute: left by a crash, and said as before
        old = time.time() - RECENT_S - 5
        os.utime(part, (old, old))
        assert main(["replay", str(logs)]) == 2
        err = capsys.readouterr().err
        assert "1 unfinished log(s) (.mcap.part): copy what they hold" in err
        assert "being recorded" not in err
    finally:
        rec.close()
    assert main(["log", "info", str(logs)]) == 0
