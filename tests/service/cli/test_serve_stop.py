"""``rlutf serve`` stopped as a whole: its process group signalled at once.

A terminal's Ctrl-C sends SIGINT to every process of the foreground group, and ``systemctl
stop`` (``KillMode=control-group``, the default), ``timeout`` and ``kill -- -PGID`` send
SIGTERM to the service's worker processes as well as to the service. The service must stop as
promptly and quietly as when only its own process is signalled: no worker taken for lost and
replaced while it stops (that held the stop up by 20 s and published ``worker_lost`` Events),
no traceback from a child process.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import pytest

from service.live.sessions import free_port

pytestmark = pytest.mark.integration


@contextlib.contextmanager
def _serving(tmp_path: Path, *flags: str) -> Iterator[tuple[subprocess.Popen[str], list[str]]]:
    """``rlutf serve`` in a process group of its own, ready; yields it and what it said on
    stderr (lines, read on until it ends when the block leaves); killed if still running."""
    argv = [
        *(sys.executable, "-m", "service", "serve", "-l", f"tcp/127.0.0.1:{free_port()}"),
        *("--store", str(tmp_path / "store"), "--no-state", *flags),
    ]
    proc = subprocess.Popen(
        [*_AS_A_TERMINAL, *argv], stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    assert proc.stderr is not None
    said: list[str] = []
    ready = threading.Event()
    reader = threading.Thread(target=_read, args=(proc.stderr, said, ready), daemon=True)
    reader.start()  # read all along: a full pipe would hold up the service's every log line
    try:
        ready.wait(180.0)
        assert any("rlutf serve: ready" in line for line in said), "".join(said)
        yield proc, said
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running 60 s after the test's signals; it said:\n{''.join(said)}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        reader.join(10.0)


def _read(stream: IO[str], said: list[str], ready: threading.Event) -> None:
    """Append each line of ``stream`` to ``said`` until it ends; set ``ready`` at the line that
    says so, or at the end."""
    for line in stream:
        said.append(line)
        if "rlutf serve: ready" in line:
            ready.set()
    ready.set()


#: Runs the command after it with the signals' defaults of one typed in a terminal (a test run
#: under ``nohup`` or from a background job hands its children SIGHUP or SIGINT ignored, and
#: an ignored signal stays ignored across ``exec``).
_AS_A_TERMINAL = (
    sys.executable,
    "-c",
    "import os, signal, sys; signal.signal(signal.SIGHUP, signal.SIG_DFL); "
    "signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])",
)


@pytest.mark.parametrize(
    "signum", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=["SIGTERM", "SIGINT", "SIGHUP"]
)
def test_a_service_whose_process_group_is_signalled_stops_at_once_and_quietly(
    tmp_path: Path, signum: int
) -> None:
    with _serving(tmp_path, "--record", str(tmp_path / "logs"), "--workers", "2") as (proc, said):
        time.sleep(2.0)  # the workers and the map checker run, idle
        os.killpg(proc.pid, signum)  # the whole group, as a terminal or systemd does
        t0 = time.monotonic()
        proc.wait(timeout=60)
        took = time.monotonic() - t0
    text = "".join(said)
    assert proc.returncode == 0, text
    assert took < 5.0, f"stopped after {took:.1f} s\n{text}"
    assert "worker_lost" not in text and "died" not in text, text
    assert "Traceback" not in text, text
    logs = sorted(p.name for p in (tmp_path / "logs").iterdir()) if signum == signal.SIGHUP else []
    assert not [name for name in logs if name.endswith(".part")], logs  # finished, not cut off


def test_a_hosts_process_leaves_a_terminals_ctrl_c_to_its_host(tmp_path: Path) -> None:
    """Ctrl-C reaches every process of the group; a host's process that stopped on it was
    taken for crashed and started again (an error in the log of every interrupted
    ``rlutf demo``), and one that a hang-up killed left its log unfinished. It stops when its
    host tells it to."""
    with _serving(tmp_path, "--no-record", "--processes", "2") as (proc, said):
        children = _processes_with(f"--host-pid\0{proc.pid}\0")
        assert len(children) == 1, children
        os.kill(children[0], signal.SIGINT)  # its share of a Ctrl-C
        os.kill(children[0], signal.SIGHUP)  # and of a closed terminal
        time.sleep(2.0)
        os.kill(children[0], 0)  # still there (raises if it ended)
        proc.send_signal(signal.SIGTERM)
    text = "".join(said)
    assert proc.returncode == 0, text
    assert "exited with code" not in text, text


def _processes_with(argument: str) -> list[int]:
    """Ids of the processes whose command line holds ``argument`` (NUL-separated words)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if argument in (entry / "cmdline").read_bytes().decode(errors="replace"):
                    found.append(int(entry.name))
            except OSError:  # ended meanwhile
                continue
    return found
