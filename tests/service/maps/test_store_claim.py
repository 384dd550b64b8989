"""One map store folder, one serving process.

Two services started from the same working directory (a second site, a test instance beside
production) both took the default ``--store store``: each checked map versions against what it
had read at its start and each overwrote the other's files, so a site's map could be replaced by
another site's map of the same id, found only at the next restart.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from service.cli.main import main
from service.maps.files import CLAIM_FILE, FileMapStore, StoreInUse


def test_a_folder_is_served_by_one_store_at_a_time(tmp_path: Path) -> None:
    first, second = FileMapStore(tmp_path), FileMapStore(tmp_path)
    first.claim()
    with pytest.raises(StoreInUse, match=rf"pid {os.getpid()}: another `rlutf serve`"):
        second.claim()
    assert FileMapStore(tmp_path).get("m1") is None  # readers need no claim
    first.release()
    second.claim()  # free again
    second.release()
    assert FileMapStore(tmp_path).ids() == []  # the claim file is no map
    assert (tmp_path / CLAIM_FILE).exists()


def test_serve_refuses_a_store_another_service_serves_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    held = FileMapStore(tmp_path / "store")
    held.claim()  # as a running service holds it
    try:
        argv = ["serve", "--store", str(tmp_path / "store"), "--no-record", "--no-state"]
        assert main([*argv, "--workers", "0", "-l", "tcp/127.0.0.1:1"]) == 1
        serve_err = capsys.readouterr().err
        # the demo too (it said "unexpected error: StoreInUse" once its service started)
        assert main(["demo", "--store", str(tmp_path / "store"), "--no-record"]) == 1
        demo_err = capsys.readouterr().err
    finally:
        held.release()
    assert "is served by another running process" in serve_err and "--no-store" in serve_err
    assert "give the demo a --store of its own" in demo_err, demo_err
    assert "Traceback" not in serve_err + demo_err and "unexpected" not in demo_err
