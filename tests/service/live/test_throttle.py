"""At most one Event per subject and interval; the last one held back goes out at its end."""

from __future__ import annotations

import pytest

from service.live import throttle as throttle_module
from service.live.throttle import EventThrottle


class _Clock:
    def __init__(self) -> None:
        self.now = 50.0

    def __call__(self) -> float:
        return self.now


def _throttle(interval_s: float = 1.0) -> tuple[EventThrottle, _Clock, list[tuple[str, ...]]]:
    clock = _Clock()
    sent: list[tuple[str, ...]] = []

    def send(level: str, code: str, key: str, message: str, stamp: int | None) -> None:
        sent.append((code, key, message, str(stamp)))

    return EventThrottle(interval_s, send, clock), clock, sent


def test_one_event_per_subject_and_code_per_interval_the_last_held_said_at_its_end() -> None:
    throttle, clock, sent = _throttle()
    for i in range(5):  # a flood of puts of m1
        throttle.say("m1", "info", "map_unchanged", "rlutf/maps/m1", f"put {i}", i)
    assert sent == [("map_unchanged", "rlutf/maps/m1", "put 0", "0")]
    assert throttle.flush() == 1.0  # the last one held back is due in a second
    clock.now += 0.4
    assert throttle.flush() == pytest.approx(0.6) and len(sent) == 1
    clock.now += 0.6
    assert throttle.flush() is None  # sent: nothing held any more
    assert sent[1] == (
        "map_unchanged",
        "rlutf/maps/m1",
        "put 4 (3 more like it since the last such Event)",
        "4",
    )
    assert throttle.held_back == 4
    # The interval starts again from the Event said at its end.
    clock.now += 0.5
    throttle.say("m1", "info", "map_unchanged", "rlutf/maps/m1", "put 5", 5)
    assert len(sent) == 2
    clock.now += 0.5
    throttle.flush()
    assert sent[2][2] == "put 5"  # one held back alone: no count


def test_subjects_and_codes_are_throttled_apart() -> None:
    throttle, _, sent = _throttle()
    throttle.say("m1", "info", "map_unchanged", "rlutf/maps/m1", "a")
    throttle.say("m1", "error", "map_version_conflict", "rlutf/maps/m1", "b")
    throttle.say("m2", "info", "map_unchanged", "rlutf/maps/m2", "c")
    assert [s[2] for s in sent] == ["a", "b", "c"]


def test_no_interval_holds_nothing_back() -> None:
    throttle, _, sent = _throttle(0.0)
    for i in range(3):
        throttle.say("m1", "info", "map_unchanged", "rlutf/maps/m1", f"put {i}")
    assert len(sent) == 3 and throttle.flush() is None


def test_invented_subjects_cost_bounded_memory_and_the_ones_held_back_are_said(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Map ids can be invented without end: past SUBJECTS_KEPT, the subjects with nothing held
    back are forgotten (at worst one more Event each); an Event held back is still said."""
    monkeypatch.setattr(throttle_module, "SUBJECTS_KEPT", 4)
    throttle, clock, sent = _throttle()
    throttle.say("m0", "info", "map_unchanged", "rlutf/maps/m0", "first")
    throttle.say("m0", "info", "map_unchanged", "rlutf/maps/m0", "held")
    for i in range(1, 10):  # within the interval
        throttle.say(f"m{i}", "info", "map_unchanged", f"rlutf/maps/m{i}", "x")
    assert len(throttle._last) <= 4
    assert [s[1] for s in sent[1:]] == [f"rlutf/maps/m{i}" for i in range(1, 10)]
    clock.now += 1.0
    throttle.flush()
    assert sent[-1][2] == "held"  # still said
