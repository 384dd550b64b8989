"""An ``RLUTF_*`` variable that names no setting is named, not passed over in silence.

Before, ``RLUTF_METRICS_PROT=9464`` (a misspelt ``RLUTF_METRICS_PORT``) left ``metrics_port`` at
its default and ``rlutf config`` and ``rlutf serve`` said nothing, while a misspelt nested one
(``RLUTF_LOCALIZER__MIN_FTI``) was refused.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from service.cli.envnames import unknown
from service.config import Settings


def _config(cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    environ = {k: v for k, v in os.environ.items() if not k.upper().startswith("RLUTF_")}
    return subprocess.run(
        [sys.executable, "-m", "service", "config"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=cwd,
        env={**environ, **env},
    )


def test_a_misspelt_variable_is_named_with_the_setting_meant(tmp_path: Path) -> None:
    done = _config(tmp_path, RLUTF_METRICS_PROT="9464")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["metrics_port"] is None
    assert "RLUTF_METRICS_PROT in the environment names no setting" in done.stderr
    assert "did you mean RLUTF_METRICS_PORT?" in done.stderr


def test_settings_and_the_variables_rlutf_reads_pass_in_silence(tmp_path: Path) -> None:
    done = _config(
        tmp_path,
        RLUTF_METRICS_PORT="9464",
        RLUTF_LOCALIZER__MIN_FIT="0.6",
        rlutf_no_store="true",  # pydantic-settings reads names in any case
        RLUTF_HEALTH_ARGS="--connect tcp/zenoh-router:7447",  # the image's health check
        RLUTF_TRACEMALLOC="0",
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert json.loads(done.stdout)["metrics_port"] == 9464


def test_unknown_looks_at_the_prefix_and_the_first_name_only() -> None:
    env = {
        "RLUTF_LOCALISER__MIN_FIT": "0.6",
        "RLUTF_ROS2__ROBOTS": "{}",
        "RLUTF_SETTINGS": "s.yaml",
        "PATH": "/bin",
        "NOT_RLUTF_X": "1",
    }
    lines = unknown(env, Settings.model_fields)
    assert len(lines) == 1
    assert lines[0].startswith("RLUTF_LOCALISER__MIN_FIT in the environment names no setting")
    assert "did you mean RLUTF_LOCALIZER?" in lines[0]
