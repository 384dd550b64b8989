"""A setting in seconds holds at most 1e9 s (``service.guard.MAX_SECONDS``).

Before, ``RLUTF_EVENT_INTERVAL_S=inf`` (or ``robot_idle_s: 1e308``) passed ``rlutf config`` and
made ``rlutf serve`` exit 1 with "unexpected error: OverflowError", and ``state_interval_s:
1e10`` started a service whose pose-state thread died at once with a traceback: no pose state.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SECONDS = (
    "state_interval_s",
    "resume_max_age_s",
    "record_max_seconds",
    "map_timeout_s",
    "max_stamp_ahead_s",
    "robot_idle_s",
    "event_interval_s",
    "handover_timeout_s",
    "handover_odom_s",
    "join_warmup_s",
)


def _rlutf(argv: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("RLUTF_")}
    return subprocess.run(
        [sys.executable, "-m", "service", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=cwd,
        env={**environ, **env},
    )


@pytest.mark.parametrize("name", SECONDS)
@pytest.mark.parametrize("value", ["inf", "1e308", "1e10"])
def test_a_duration_past_1e9_s_is_named(tmp_path: Path, name: str, value: str) -> None:
    done = _rlutf(["config"], tmp_path, **{f"RLUTF_{name.upper()}": value})
    assert done.returncode == 2, done.stderr
    assert f"{name}: Input should be less than or equal to 1000000000" in done.stderr
    assert value in done.stderr
    assert "Traceback" not in done.stderr


def test_serve_refuses_it_before_it_starts(tmp_path: Path) -> None:
    (tmp_path / "s.yaml").write_text("event_interval_s: .inf\n")
    argv = ["serve", "--settings", "s.yaml", "--listen", "tcp/127.0.0.1:0", "--workers", "0"]
    done = _rlutf(argv, tmp_path)
    assert done.returncode == 2, done.stderr
    assert "event_interval_s" in done.stderr
    assert "unexpected error" not in done.stderr
    assert not (tmp_path / "store").exists()  # refused before anything is made


def test_1e9_s_is_still_accepted(tmp_path: Path) -> None:
    env = {f"RLUTF_{name.upper()}": "1e9" for name in SECONDS}
    assert _rlutf(["config"], tmp_path, **env).returncode == 0
