"""Scenario logs: WIRE.md's MCAP layout, round-tripped; CARMEN odometry re-anchoring undone."""

from __future__ import annotations

import io
import json
from importlib import resources

import numpy as np
import pytest
from mcap.reader import make_reader

from bench.carmen import raw_odometry
from bench.logs import TRUTH_SCHEMA, write_log
from bench.scenarios import Scenario, simulate
from rlutf.motion import compose, relative
from rlutf.sim import LidarModel
from schemas import InitialPose, LaserScan, Map, Odometry, decode

MODELS = {
    "rlutf.Map": Map,
    "rlutf.Odometry": Odometry,
    "rlutf.InitialPose": InitialPose,
    "rlutf.LaserScan": LaserScan,
}


def test_log_layout_round_trips() -> None:
    run = simulate(Scenario("logtest", "t", steps=6, lidar=LidarModel(beams=90, dropout=0.2)), 3)
    buf = io.BytesIO()
    count = write_log(run, buf)
    buf.seek(0)
    seen: dict[str, list[tuple[int, int, object]]] = {}
    for schema, channel, message in make_reader(buf).iter_messages(log_time_order=True):
        assert schema is not None and channel.message_encoding == "json"
        assert schema.encoding == "jsonschema"
        if schema.name in MODELS:
            expected = resources.files("schemas").joinpath("jsonschema", f"{schema.name}.json")
            assert schema.data == expected.read_bytes()
            value: object = decode(MODELS[schema.name], message.data)
        else:
            assert schema.name == TRUTH_SCHEMA
            value = json.loads(message.data)
        seen.setdefault(channel.topic, []).append((message.log_time, message.publish_time, value))
    assert sum(len(v) for v in seen.values()) == count
    assert set(seen) == {
        f"rlutf/maps/{run.map_id}",
        "rlutf/robots/r1/initialpose",
        "rlutf/robots/r1/odom",
        "rlutf/robots/r1/scan",
        "/bench/robots/r1/truth",
    }
    scans = seen["rlutf/robots/r1/scan"]
    assert len(scans) == run.updates
    for k, (log_ns, pub_ns, msg) in enumerate(scans, start=1):
        assert isinstance(msg, LaserScan)
        assert pub_ns == msg.stamp_ns == run.stamps_ns[k] and log_ns > pub_ns
        got = np.array([np.nan if r is None else r for r in msg.ranges])
        np.testing.assert_array_equal(got, run.scans[k].ranges)
    odom = [m for _, _, m in seen["rlutf/robots/r1/odom"]]
    assert len(odom) == run.updates + 1
    np.testing.assert_array_equal(
        [[o.x, o.y, o.theta] for o in odom if isinstance(o, Odometry)], run.odometry
    )
    start = seen["rlutf/robots/r1/initialpose"][0][2]
    assert isinstance(start, InitialPose) and start.map_id == run.map_id
    assert [start.x, start.y, start.theta] == run.truth[0].tolist()
    truth = [m for _, _, m in seen["/bench/robots/r1/truth"]]
    np.testing.assert_array_equal(
        [[t["x"], t["y"], t["theta"]] for t in truth if isinstance(t, dict)], run.truth[1:]
    )
    # The map comes first, the initial pose after the odometry it is anchored to.
    first_map = seen[f"rlutf/maps/{run.map_id}"][0][0]
    assert (
        first_map < seen["rlutf/robots/r1/odom"][0][0] < seen["rlutf/robots/r1/initialpose"][0][0]
    )


def test_carmen_odometry_reanchoring_is_undone() -> None:
    text = "\n".join(
        [
            "ODOM 0 0 0 0 0 0 1.0 h 1.0",
            "ODOM 1 0 0 0 0 0 2.0 h 2.0",
            "FLASER 2 1 1 5 5 0.3 5 5 0.3 2.0 h 2.0",
            "ODOM 5 5 0.3 0 0 0 0 h 0",  # re-anchored at the corrected pose
            "ODOM 5.5 5 0.3 0 0 0 2.5 h 2.5",
            "FLASER 2 1 1 6 5 0.3 6 5 0.3 2.5 h 2.5",
        ]
    )
    stream, at_scan = raw_odometry(text)
    assert at_scan.tolist() == [1, 3]
    np.testing.assert_allclose(stream[1, 1:], [1.0, 0.0, 0.0])
    # After the jump the readings continue from where the robot's own odometry was.
    expected = compose(np.array([1.0, 0.0, 0.0]), relative([5, 5, 0.3], [5.5, 5, 0.3]))
    np.testing.assert_allclose(stream[3, 1:], expected)
    assert stream[2, 1:] == pytest.approx(stream[1, 1:])
