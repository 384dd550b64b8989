"""bench.restart's reading of a run: a robot's next scan is the first one the new service can
receive (ready, and the robot's session connected to it again)."""

from __future__ import annotations

import math

from bench.restart import figures

S = 1_000_000_000


def test_next_scan_waits_for_ready_and_the_session_reconnected() -> None:
    raw = {
        "ids": ["r0", "r1"],
        "sessions": 2,  # robot i on session i % 2
        "killed": 10 * S,
        "up": 15 * S,
        # session 0 back 1 s after ready, session 1 already connected when ready came
        "links": [
            (0, 10 * S + 5, False),
            (1, 10 * S + 7, False),
            (1, 14 * S, True),
            (0, 16 * S, True),
        ],
        "puts": [
            (0, 9 * S),
            (1, 9 * S),
            (0, 15 * S + S // 2),
            (1, 15 * S + S // 10),
            (0, 16 * S + S // 10),
        ],
        "poses": [("r0", 9 * S + 1), ("r1", 15 * S + S // 2), ("r0", 16 * S + S // 2)],
    }
    f = figures(raw)
    assert f["resumed"] == 2
    assert math.isclose(f["down_s"], 5.0)
    assert math.isclose(f["reconnect_s"], 1.0)  # session 0, a second after ready
    # r1: next scan 15.1 s, pose 15.5 s; r0: its scan at 15.5 s went nowhere, next at 16.1 s
    assert sorted(round(float(x), 3) for x in f["after_scan"]) == [0.4, 0.4]
    assert f["within_2s"] == 2
    assert sorted(round(float(x), 3) for x in f["after_kill"]) == [5.5, 6.5]


def test_a_robot_without_a_pose_from_the_new_service_is_not_resumed() -> None:
    raw = {
        "ids": ["r0"],
        "sessions": 1,
        "killed": 10 * S,
        "up": 12 * S,
        "links": [],
        "puts": [(0, 13 * S)],
        "poses": [("r0", 9 * S)],  # before the kill: the old service's
    }
    f = figures(raw)
    assert f["resumed"] == 0 and f["within_2s"] == 0
    assert math.isnan(float(f["after_scan"][0]))
