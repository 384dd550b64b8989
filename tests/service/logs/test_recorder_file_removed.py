"""A log removed while it is written (by hand, or with its folder) is noticed at the next flush,
not at its rotation up to an hour later."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from mcaplog_fixtures import read_all

from schemas import Event, EventCode, decode
from service.logs import mcaplog
from service.logs.mcaplog import McapRecorder

CONFIG = {"prefix": "rlutf", "instance": "t1"}


def _until(check: Callable[[], object], seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while not check() and time.monotonic() < deadline:
        time.sleep(0.02)


@pytest.mark.parametrize("what", ["file", "folder"])
def test_a_log_removed_while_written_is_said_and_recording_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, what: str
) -> None:
    monkeypatch.setattr(mcaplog, "RETRY_S", 0.3)
    folder = tmp_path / "logs"
    # rotation an hour away, as by default: before, the removal went unnoticed until then
    rec = McapRecorder(folder, instance="t1", flush_interval_s=0.05)
    published: list[Event] = []
    rec.on_event = published.append
    rec.set_config(CONFIG)
    sent = 0

    def odometry(n: int) -> None:
        nonlocal sent
        for _ in range(n):
            sent += 1
            rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', sent, sent)
            time.sleep(0.01)

    odometry(5)
    _until(lambda: rec.current_path is not None)
    part = rec.current_path
    assert part is not None
    if what == "file":
        part.unlink()
    else:
        shutil.rmtree(folder)
    _until(lambda: odometry(1) or published, 2.0)
    assert [e.code for e in published] == [EventCode.RECORDING_FAILED], published
    assert str(part) in published[0].message and "removed" in published[0].message
    if what == "folder":
        odometry(40)  # past the retry delay: the folder is not made again
        assert not folder.exists() and len(published) == 1
        folder.mkdir()
    _until(lambda: odometry(5) or len(published) == 2)
    rec.close()
    assert [e.code for e in published] == [
        EventCode.RECORDING_FAILED,
        EventCode.RECORDING_RESUMED,
    ]
    (last,) = rec.files
    logged = [decode(Event, r.payload) for r in read_all(last, ["rlutf.Event"])]
    assert logged == [published[1]]  # the gap is in the audit trail
    assert len(read_all(last, ["rlutf.Odometry"])) > 0
