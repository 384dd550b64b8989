"""A recorder on a full disk: its retries open a file each, which the full disk leaves empty and
the recorder removes; the run's file numbers skip one for the gap, not one per retry.

Needs a small real file system: a tmpfs mounted here (root only; skipped otherwise).
"""

from __future__ import annotations

import contextlib
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from schemas import Event, EventCode
from service.logs import mcaplog
from service.logs.mcaplog import McapRecorder
from service.logs.runs import group_runs


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    folder = tmp_path / "small"
    folder.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(folder)],
        capture_output=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip("no tmpfs could be mounted (needs root)")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


def _fill(folder: Path) -> Path:
    filler = folder / "filler"
    with contextlib.suppress(OSError), filler.open("wb") as f:
        while True:
            f.write(b"\0" * 4096)
            f.flush()
    return filler


def _until(check: Callable[[], object], seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while not check() and time.monotonic() < deadline:
        time.sleep(0.02)


def test_retries_on_a_full_disk_take_no_file_number(
    small_disk: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mcaplog, "RETRY_S", 0.1)
    folder = small_disk / "logs"
    rec = McapRecorder(folder, instance="t1", flush_interval_s=0.05)
    published: list[Event] = []
    rec.on_event = published.append
    rec.set_config({"prefix": "rlutf", "instance": "t1"})
    sent = 0

    def odometry(n: int) -> None:
        nonlocal sent
        for _ in range(n):
            sent += 1
            rec.record("rlutf/robots/r1/odom", "rlutf.Odometry", b'{"stamp_ns":0}', sent, sent)
            time.sleep(0.01)

    odometry(10)
    _until(lambda: rec.current_path is not None and rec.current_path.stat().st_size > 0)
    filler = _fill(small_disk)
    _until(lambda: odometry(1) or published)
    assert [e.code for e in published] == [EventCode.RECORDING_FAILED]
    odometry(100)  # a second: some ten retries, each opening a file the disk leaves empty
    assert rec.errors > 3, rec.errors
    filler.unlink()
    _until(lambda: odometry(1) or len(published) == 2)
    rec.close()
    assert [e.code for e in published][-1] == EventCode.RECORDING_RESUMED
    # file 0, the one the disk filled, is left as it was (a .part for `rlutf log recover`);
    # the gap takes one number (before, each retry took one more: 11 here)
    (run,) = group_runs(sorted(folder.glob("*.mcap")))
    assert run.skipped == [1], run.skipped
    (part,) = folder.glob("*.part")
    assert part.name.endswith("-001.mcap.part")
