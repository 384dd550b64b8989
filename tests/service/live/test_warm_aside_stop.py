"""A service told to stop while a child compiles the localizer's kernels stops at once, and the
child does not outlive it (a first start after an install, under SIGTERM or ``kill -9``).

Before, ``rlutf serve`` sat in the child's compile, its SIGTERM unheard, until the compile ended
(minutes on a busy host: a supervisor's grace period ran out, then ``kill -9`` left the child
compiling on its own). Real ``rlutf serve`` processes, a real empty numba cache.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.live.warmaside import COMPILING


def _children(pid: int) -> set[int]:
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            found |= {int(c) for c in (task / "children").read_text().split()}
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _compiling(tmp_path: Path, *layout: str) -> tuple[subprocess.Popen[str], int]:
    """A client-mode ``rlutf serve`` on an empty numba cache, once its child compiles."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--mode",
            "client",
            "-e",
            "tcp/127.0.0.1:9",
            "--no-store",
            "--workers",
            "0",
            "--record",
            str(tmp_path / "logs"),
            "--state",
            str(tmp_path / "state"),
            "--instance",
            "warm",
            *layout,
        ],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    line = proc.stderr.readline()
    assert COMPILING in line, line
    end = time.monotonic() + 20.0
    while not (children := _children(proc.pid)) and time.monotonic() < end:
        time.sleep(0.05)
    assert len(children) == 1, children
    time.sleep(1.0)  # the child is well into its compile
    return proc, children.pop()


@pytest.mark.parametrize(
    "layout", [(), ("--processes", "1")], ids=["one process", "a host of processes"]
)
def test_sigterm_while_the_kernels_compile_stops_the_service_and_its_child(
    tmp_path: Path, layout: tuple[str, ...]
) -> None:
    """Exit 0, as any stop (a host, the default layout, took it for a failure: exit 1)."""
    proc, child = _compiling(tmp_path, *layout)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
        if _alive(child):
            os.kill(child, signal.SIGKILL)
    assert rc == 0
    assert time.monotonic() - t0 < 10.0
    assert not _alive(child)


def test_a_killed_service_s_compiling_child_ends_too(tmp_path: Path) -> None:
    proc, child = _compiling(tmp_path)
    proc.kill()
    proc.wait()
    end = time.monotonic() + 5.0
    while _alive(child) and time.monotonic() < end:
        time.sleep(0.1)
    try:
        assert not _alive(child)
    finally:
        if _alive(child):
            os.kill(child, signal.SIGKILL)
