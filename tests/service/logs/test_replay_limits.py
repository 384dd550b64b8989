"""Replay applies the input limits of service.guard as the live service does (issue 19)."""

from __future__ import annotations

import json
from pathlib import Path

from mcaplog_fixtures import T0, read_all, simulated_inputs, write_log

from schemas import Odometry, encode
from service.logs.mcapfile import Record
from service.logs.replay import replay


def test_replay_refuses_what_the_live_service_refused(tmp_path: Path) -> None:
    """The limits are the engine's: a log holding inputs over a limit replays with the same
    Events, and the other inputs give the poses they give without them."""
    records = simulated_inputs(("r1",), steps=6)
    extreme = Odometry(stamp_ns=T0 + 250_000_000, x=1e308, y=0.0, theta=0.0)
    at = T0 + 250_000_000
    bad = Record("rlutf/robots/r1/odom", "rlutf.Odometry", encode(extreme), at, at)
    attacked = sorted([*records, bad], key=lambda r: r.log_time_ns)
    a = replay([write_log(tmp_path / "a.mcap", attacked)], tmp_path / "out.mcap")
    b = replay([write_log(tmp_path / "b.mcap", records)])
    assert a.rejected == 1 and b.rejected == 0
    assert [p.payload for p in a.recomputed["r1"]] == [p.payload for p in b.recomputed["r1"]]
    events = [json.loads(r.payload) for r in read_all(tmp_path / "out.mcap", ["rlutf.Event"])]
    assert [e["code"] for e in events if e["code"] == "invalid_message"] == ["invalid_message"]
    assert all(r.payload for r in read_all(tmp_path / "out.mcap", ["rlutf.Event"]))
    again = replay([tmp_path / "out.mcap"])
    assert again.rejected == 1
