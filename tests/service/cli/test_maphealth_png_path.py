"""`rlutf map health ID --png PATH` checks PATH before any work, as every other output flag.

A PNG in a missing folder was found out only after the MapHealth was fetched and printed:
"unexpected error: MapFileError ... report it", exit 1, where `map show --out`, `map import
--png` and `map build --png` say at once which folder is missing, exit 2.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from service.cli.main import main


def test_a_png_in_a_missing_folder_is_refused_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    png = tmp_path / "missing" / "health.png"
    logs = tmp_path / "no-such-log.mcap"  # never read: the flag is checked first
    assert main(["map", "health", "m1", "--log", str(logs), "--png", str(png)]) == 2
    err = capsys.readouterr().err
    assert f"--png {png}" in err and "does not exist" in err, err
    assert "unexpected error" not in err


def test_the_png_is_checked_before_the_service_is_asked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    png = tmp_path / "missing" / "health.png"
    code = main(["map", "health", "m1", "-e", "tcp/127.0.0.1:1", "--png", str(png)])
    err = capsys.readouterr().err
    assert code == 2 and f"--png {png}" in err, err
