"""Fixtures for service tests: a real service and real Zenoh client sessions on loopback."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from service_harness import Bench, running_bench


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path) as b:
        yield b


@pytest.fixture(autouse=True)
def _no_settings_file_after(monkeypatch: pytest.MonkeyPatch) -> None:
    """``load_settings`` hands ``--settings FILE`` to the processes it starts through
    ``RLUTF_SETTINGS``, in this process's environment: set first, so that monkeypatch restores
    the variable's absence after each test (a test's settings file read by every later test of
    the worker made ``test_without_the_ros_front_door_the_variable_stops_nothing`` fail)."""
    monkeypatch.setenv("RLUTF_SETTINGS", "")
    monkeypatch.delenv("RLUTF_SETTINGS")
