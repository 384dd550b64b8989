"""A service process declares the robot keys it takes in (so Zenoh keeps their routes), a bounded
number of them, and starts again with the keys it keeps split."""

from __future__ import annotations

from pathlib import Path

import pytest
from service_harness import Bench, running_bench, wait_until

from schemas import Odometry, encode
from service.live import intake as intake_module


def _odometry(bench: Bench, robots: range) -> None:
    for i in robots:
        payload = encode(Odometry(stamp_ns=1_000 + i, x=0.0, y=0.0, theta=0.0))
        bench.client.put(f"rlutf/robots/r{i:03d}/odom", payload)


def test_the_keys_taken_in_are_declared_up_to_a_bound_and_again_after_a_reset(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(intake_module, "KEYS_DECLARED", 8)
    monkeypatch.setattr(intake_module, "KEYS_SPLIT", 20)
    with running_bench(tmp_path, intake="loop") as bench:
        intake = bench.service.intake
        received = lambda: bench.service.stats.received  # noqa: E731
        _odometry(bench, range(12))
        assert wait_until(lambda: received() >= 12), received()
        # every input taken in, the first eight keys declared and kept
        assert len(intake._declared) == 8
        assert {str(k) for k in intake._declared} <= {
            f"rlutf/robots/r{i:03d}/odom" for i in range(12)
        }
        _odometry(bench, range(12, 30))  # past KEYS_SPLIT: the split keys start again
        assert wait_until(lambda: received() >= 30), received()
        assert 0 < len(intake._declared) <= 8
        assert all(str(k) >= "rlutf/robots/r020/odom" for k in intake._declared)


def test_a_callback_intake_declares_nothing(tmp_path: Path) -> None:
    """Zenoh's callbacks may not call Zenoh (declaring from one can wait on the link): with the
    callback intake the keys are left undeclared."""
    with running_bench(tmp_path, intake="callback") as bench:
        _odometry(bench, range(3))
        assert wait_until(lambda: bench.service.stats.received >= 3)
        assert bench.service.intake._declared == []
