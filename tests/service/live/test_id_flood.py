"""A flood of made-up robot ids: bounded Events and log lines, no waiting list of fakes, and the
real fleet still answered.

10,000 puts on 10,000 made-up ids in a quarter of a second were about 2,300 Events, each a
WARNING line of the service's log (the per-robot bound holds back nothing when every id is
new), and the made-up ids that sent a valid scan stayed listed as waiting robots for
``robot_idle_s``. Now the Events of a code go out for at most ``ROBOTS_PER_WINDOW`` robots a
second (:mod:`service.live.eventbudget`), the rest said in one Event on ``{prefix}/events``.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path

import pytest
from service_harness import Collector, running_bench, wait_until

from schemas import Event, encode
from service.live.eventbudget import ROBOTS_PER_WINDOW, WINDOW_NS, EventBudget
from service.live.robots import RobotView

FOLDED = re.compile(r"^(\d+) more like it from (\d+) robots")


def test_the_budget_lets_out_a_bounded_number_of_robots_per_code_and_counts_the_rest() -> None:
    budget = EventBudget(robots=3, window_ns=1_000)
    said = [budget.admit(f"f{k}", "error", "invalid_message", "k", "bad", k) for k in range(10)]
    assert said == [True] * 3 + [False] * 7
    assert budget.admit("f1", "error", "invalid_message", "k", "bad", 11), "a robot let out"
    assert budget.admit("f9", "warning", "not_initialized", "k", "m", 12), "another code"
    assert budget.admit("f9", "info", "relocalized", "k", "m", 13), "a code no flood makes"
    for k in range(5):  # an operator's request is answered each time
        assert budget.admit(
            f"g{k}", "error", "invalid_message", "rlutf/robots/g/initialpose", "", k
        )
    assert budget.admit("f8", "error", "invalid_message", "k", "bad again", 500) is False
    assert budget.due(999) == [], "said once the window is over"
    (folded,) = budget.due(1_000)
    assert folded.code == "invalid_message" and folded.about == "k"
    assert folded.message.startswith("8 more like it from 7 robots")
    assert folded.message.endswith("the last: bad again")
    assert budget.due(5_000) == [] and budget.held_back == 8
    assert budget.admit("f7", "error", "invalid_message", "k", "bad", 5_000), "a new window"


def _not_initialized(at: int) -> bytes:
    return encode(Event(stamp_ns=at, level="warning", code="not_initialized", message="x"))


def test_a_robot_never_placed_is_listed_only_while_its_scans_keep_coming() -> None:
    now = [10**18]
    view = RobotView("a", {}, lambda: now[0])
    view.unplaced_ns = 3_000_000_000
    view.event("real", _not_initialized(now[0]), now[0])
    view.event("fake", _not_initialized(now[0]), now[0])
    view.initialized("placed", now[0])  # placed by an operator: listed until its first pose
    for _ in range(4):  # the real one scans on, an Event each event_interval_s
        now[0] += 1_000_000_000
        view.event("real", _not_initialized(now[0]), now[0])
    assert [w.robot_id for w in view.waiting()] == ["placed", "real"]


@pytest.mark.integration
def test_a_flood_of_new_robot_ids_costs_bounded_events_and_the_fleet_is_answered(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fakes = 2000
    with caplog.at_level(logging.WARNING), running_bench(tmp_path, event_interval_s=1.0) as b:
        b.service.robot_view.unplaced_ns = 1_500_000_000  # the default, 10 s, is long to wait
        events, poses = Collector(), Collector()
        subs = [
            b.client.declare_subscriber("rlutf/events", events),
            b.client.declare_subscriber("rlutf/robots/*/events", events),
            b.client.declare_subscriber("rlutf/robots/real/pose", poses),
        ]
        b.put_map()
        time.sleep(0.3)
        real = b.robot("real", 1, steps=120)
        real.initial_pose("m1")
        time.sleep(0.3)
        stop = threading.Event()

        def drive() -> None:
            while not stop.is_set() and real.step < 100:
                real.advance()
                time.sleep(0.1)

        driver = threading.Thread(target=drive)
        driver.start()
        time.sleep(0.5)
        valid = encode(real.scan_msg(1))
        caplog.clear()
        flood_at = time.monotonic()
        for i in range(fakes):  # half malformed, half valid scans of robots never placed
            payload = b'{"stamp_ns": 1' if i % 2 else valid
            b.client.put(f"rlutf/robots/fake{i}/scan", payload)
        flood_s = time.monotonic() - flood_at
        during = real.step

        def folded_codes() -> set[object]:
            return {e["code"] for e in events.on("rlutf/events") if FOLDED.match(str(e["message"]))}

        # the folded Events are said at the end of their window (later on a loaded machine)
        time.sleep(2.5)
        wait_until(lambda: folded_codes() >= {"invalid_message", "not_initialized"}, 15.0)
        stop.set()
        driver.join()
        for sub in subs:
            sub.undeclare()

        fake_events = [
            e for k, got in events.samples.items() if k.startswith("rlutf/robots/fake") for e in got
        ]
        codes = {e["code"] for e in fake_events}
        assert codes <= {"invalid_message", "not_initialized"}, codes
        # per code at most ROBOTS_PER_WINDOW robots a window, over the windows the flood spans
        windows = int(flood_s / (WINDOW_NS / 1e9)) + 2
        bound = 2 * windows * ROBOTS_PER_WINDOW
        assert len(fake_events) <= bound, (len(fake_events), bound, flood_s)
        summaries = [e for e in events.on("rlutf/events") if FOLDED.match(str(e["message"]))]
        assert {e["code"] for e in summaries} == {"invalid_message", "not_initialized"}
        assert len(summaries) <= 2 * windows
        # every malformed one is either an Event of its robot or counted in a summary
        sent = sum(e["code"] == "invalid_message" for e in fake_events)
        folded = [FOLDED.match(str(e["message"])) for e in summaries]
        counted = sum(
            int(m.group(1))
            for m, e in zip(folded, summaries, strict=True)
            if m and e["code"] == "invalid_message"
        )
        assert sent + counted == b.service.stats.rejected, (sent, counted)
        assert b.service.stats.rejected > fakes // 4, "the flood reached the service"
        # the service's log: a line per Event sent, not per input
        lines = [r for r in caplog.records if r.name == "service.live.publishing"]
        assert len(lines) <= bound + 2 * windows, len(lines)
        # the real robot was answered through the flood: its last scan, and all but a few
        answered = lambda: {p["stamp_ns"] for p in poses.on("rlutf/robots/real/pose")}  # noqa: E731
        assert poses.wait_for(lambda: real.stamp(real.step) in answered())
        since = {real.stamp(i) for i in range(during, real.step + 1)}
        assert len(since & answered()) >= 0.9 * len(since), (len(since & answered()), len(since))
        # the made-up ids that sent a valid scan are not listed as waiting for robot_idle_s
        waiting = [w.robot_id for w in b.service.robot_view.waiting()]
        assert not [r for r in waiting if r.startswith("fake")], waiting[:5]


@pytest.mark.integration
def test_made_up_ids_that_fill_max_robots_give_way_soon_and_placed_robots_stay(
    tmp_path: Path,
) -> None:
    # A burst of valid scans on made-up ids filled max_robots, and every real new robot was
    # refused for robot_idle_s (an hour). A robot never placed is evicted after a short idle.
    with running_bench(tmp_path, max_robots=30, event_interval_s=0.0) as b:
        b.service.sweeper.unplaced_ns = 1_500_000_000  # the default, 10 s, is long to wait
        events, poses = Collector(), Collector()
        subs = [
            b.client.declare_subscriber("rlutf/events", events),
            b.client.declare_subscriber("rlutf/robots/*/events", events),
            b.client.declare_subscriber("rlutf/robots/late/pose", poses),
        ]
        b.put_map()
        time.sleep(0.3)
        early = b.robot("early", 1)
        early.initial_pose("m1")  # placed, and silent from here on: kept for robot_idle_s
        valid = encode(b.robot("fake", 2).scan_msg(1))
        for i in range(40):
            b.client.put(f"rlutf/robots/fake{i}/scan", valid)
        assert events.wait_for(
            lambda: any(e["code"] == "robot_limit" for e in events.on("rlutf/events"))
        )
        late = b.robot("late", 3)
        # (an InitialPose of "late" now would take a made-up id's place at once: the next test)
        assert b.service.holds("early")
        evicted = lambda: [  # noqa: E731
            e
            for k, got in events.samples.items()
            if k.startswith("rlutf/robots/fake")
            for e in got
            if e["code"] == "robot_evicted"
        ]
        assert wait_until(lambda: b.service.sweeper.evicted == 29, 10.0), b.service.sweeper.evicted
        assert wait_until(evicted, 5.0)  # the Events cross the bus after the count
        assert all("never placed" in e["message"] for e in evicted())
        late.initial_pose("m1")
        for _ in range(10):
            late.advance()
            time.sleep(0.1)
        assert poses.wait_for(lambda: len(poses.on("rlutf/robots/late/pose")) >= 5)
        assert b.service.holds("early"), "a placed robot idle for 4 s was evicted"
        for sub in subs:
            sub.undeclare()


@pytest.mark.integration
def test_a_robot_being_placed_takes_the_place_of_one_never_placed(tmp_path: Path) -> None:
    # made-up ids that keep coming hold max_robots full however soon they are evicted: an
    # InitialPose of a new robot evicts one of them rather than be refused
    with running_bench(tmp_path, max_robots=10, event_interval_s=0.0) as b:
        events = Collector()
        sub = b.client.declare_subscriber("rlutf/robots/*/events", events)
        b.put_map()
        time.sleep(0.3)
        valid = encode(b.robot("fake", 2).scan_msg(1))
        for i in range(10):
            b.client.put(f"rlutf/robots/fake{i}/scan", valid)
        assert wait_until(lambda: b.service.robots_held() == 10, 5.0)
        b.client.put("rlutf/robots/fake10/scan", valid)  # refused: full
        time.sleep(0.3)
        assert not b.service.holds("fake10")
        b.robot("late", 3).initial_pose("m1")
        assert wait_until(lambda: b.service.holds("late"), 5.0)
        assert b.service.robots_held() == 10 and b.service.sweeper.evicted == 1
        assert not b.service.holds("fake0"), "the first seen goes"
        made_room = lambda: [  # noqa: E731
            e for e in events.on("rlutf/robots/fake0/events") if e["code"] == "robot_evicted"
        ]
        assert events.wait_for(lambda: len(made_room()) == 1)
        assert "to make room" in made_room()[0]["message"]
        sub.undeclare()
