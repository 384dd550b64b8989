"""The simulated fleet's schedule: every robot's steps in time order, none early, and a stop."""

from __future__ import annotations

import threading
import time

from service.sim.fleet import drive


def test_steps_come_in_time_order_staggered_and_never_early() -> None:
    calls: list[tuple[int, int, float]] = []
    steps: list[int] = []
    start = time.monotonic()
    sent, last, _ = drive(
        3, 0.03, lambda r, k: calls.append((r, k, time.monotonic())), 4, on_step=steps.append
    )
    assert sent == 12 and last == 4 and steps == [1, 2, 3, 4]
    assert [(r, k) for r, k, _ in calls] == [(r, k) for k in range(1, 5) for r in range(3)]
    for r, k, at in calls:
        assert at - start >= (k - 1 + r / 3) * 0.03 - 1e-4


def test_a_run_without_an_end_stops_when_asked() -> None:
    stop = threading.Event()
    calls: list[tuple[int, int]] = []

    def send(robot: int, step: int) -> None:
        calls.append((robot, step))
        if step == 3 and robot == 1:
            stop.set()

    sent, last, _ = drive(2, 0.01, send, None, stop)
    assert calls[-1] == (1, 3) and sent == len(calls) == 6 and last == 3
