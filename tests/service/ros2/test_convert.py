"""CDR to WIRE.md messages and back, against messages built with rosbags directly."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from ros_client import TS, initialpose_msg, odom_msg, tf_msg, yaw

from schemas import LaserScan, Odometry, PoseEstimate, SchemaError, decode
from service.ros2 import convert


def _scan(ranges: list[float]) -> bytes:
    t = TS.types
    msg = t["sensor_msgs/msg/LaserScan"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=5), frame_id="laser"
        ),
        angle_min=-1.0,
        angle_max=1.0,
        angle_increment=0.5,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.1,
        range_max=10.0,
        ranges=np.asarray(ranges, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))


def test_laser_scan_with_no_returns_as_nan_and_inf() -> None:
    s = convert.laser_scan(_scan([1.5, math.nan, math.inf, -math.inf, 2.25]))
    assert s.stamp_ns == 1_700_000_000_000_000_005
    assert s.ranges == (1.5, None, None, None, 2.25)
    assert (s.angle_min, s.angle_increment, s.range_min) == (-1.0, 0.5, pytest.approx(0.1))


def test_bad_cdr_and_bad_fields_are_schema_errors() -> None:
    with pytest.raises(SchemaError, match="malformed CDR"):
        convert.laser_scan(b"\x00\x01\x00\x00\x01")
    raw = bytearray(_scan([1.0]))
    with pytest.raises(SchemaError, match="malformed CDR"):
        convert.odometry(bytes(raw[:20]))
    good = _scan([1.0, 2.0])
    bad = TS.deserialize_cdr(good, "sensor_msgs/msg/LaserScan")
    bad.angle_increment = 0.0
    with pytest.raises(SchemaError, match="angle_increment"):
        convert.laser_scan(bytes(TS.serialize_cdr(bad, "sensor_msgs/msg/LaserScan")))


def test_odometry_tf_and_initial_pose() -> None:
    pose = np.array([1.0, -2.0, 2.5])
    raw = bytes(TS.serialize_cdr(odom_msg(pose, 42), "nav_msgs/msg/Odometry"))
    o = convert.odometry(raw)
    assert (o.stamp_ns, o.x, o.y) == (42, 1.0, -2.0) and o.theta == pytest.approx(2.5, abs=1e-12)
    wheel = odom_msg(pose, 42, "/wheel_odom", "base_link")
    raw_wheel = bytes(TS.serialize_cdr(wheel, "nav_msgs/msg/Odometry"))
    assert convert.odometry_in_frames(raw_wheel) == (o, "wheel_odom", "base_link")
    tf = bytes(
        TS.serialize_cdr(tf_msg(pose, 7, "/odom", "base_footprint"), "tf2_msgs/msg/TFMessage")
    )
    assert [m.x for m in convert.odometry_from_tf(tf, "odom", "base_footprint")] == [1.0]
    assert convert.odometry_from_tf(tf, "odom", "base_link") == []
    found, frames = convert.odometry_from_tf_in_frames(tf, "odom", "base_link")
    assert (found, frames) == ([], [("odom", "base_footprint")])
    ip = bytes(
        TS.serialize_cdr(initialpose_msg(pose, 9), "geometry_msgs/msg/PoseWithCovarianceStamped")
    )
    p = convert.initial_pose(ip, "m1")
    assert (p.map_id, p.x, p.stamp_ns) == ("m1", 1.0, 9)
    wrong = initialpose_msg(pose, 9, "odom")
    raw_wrong = bytes(TS.serialize_cdr(wrong, "geometry_msgs/msg/PoseWithCovarianceStamped"))
    with pytest.raises(SchemaError, match="frame_id"):
        convert.initial_pose(raw_wrong, "m1")


def test_amcl_pose_and_transform_decode_with_rosbags() -> None:
    cov = (0.04, 0.01, 0.002, 0.01, 0.09, 0.003, 0.002, 0.003, 0.0025)
    pose = PoseEstimate(
        stamp_ns=1_700_000_000_123_456_789,
        robot_id="r1",
        map_id="m1",
        x=3.0,
        y=4.0,
        theta=-2.0,
        status="corrected",
        discrepancy=0.01,
        iterations=2,
        covariance=cov,
    )
    m = TS.deserialize_cdr(convert.amcl_pose(pose), "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert m.header.frame_id == "map"
    assert (m.pose.pose.position.x, m.pose.pose.position.y) == (3.0, 4.0)
    assert yaw(m.pose.pose.orientation) == pytest.approx(-2.0)
    c = m.pose.covariance.reshape(6, 6)
    idx = [0, 1, 5]
    assert np.array_equal(c[np.ix_(idx, idx)], np.reshape(cov, (3, 3)))
    assert np.count_nonzero(c) == 9
    tf = TS.deserialize_cdr(
        convert.transform([1.0, 2.0, 0.5], 10, "map", "odom"), "tf2_msgs/msg/TFMessage"
    )
    t = tf.transforms[0]
    assert (t.header.frame_id, t.child_frame_id, t.header.stamp.nanosec) == ("map", "odom", 10)
    assert yaw(t.transform.rotation) == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("status", "score", "level", "initialized"),
    [("tracking", 0.97, 0, "true"), ("corrected", 0.3, 1, "true"), ("lost", 0.2, 2, "false")],
)
def test_quality_as_diagnostics_decodes_with_rosbags(
    status: str, score: float, level: int, initialized: str
) -> None:
    pose = PoseEstimate(
        stamp_ns=1_700_000_000_000_000_007,
        robot_id="r1",
        map_id="m1",
        x=1.0,
        y=2.0,
        theta=0.0,
        status=status,  # type: ignore[arg-type]
        discrepancy=0.01,
        iterations=0,
        localization_score=score,
        deviation_range=0.0123,
    )
    m = TS.deserialize_cdr(convert.quality_diagnostics(pose), "diagnostic_msgs/msg/DiagnosticArray")
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 7)
    (s,) = m.status
    assert (s.level, s.name, s.hardware_id, s.message) == (
        level,
        "rlutf: localization",
        "r1",
        status,
    )
    values = {kv.key: kv.value for kv in s.values}
    assert float(values["localization_score"]) == score
    assert float(values["deviation_range"]) == 0.0123
    assert (values["position_initialized"], values["map_id"]) == (initialized, "m1")


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@given(
    ranges=st.lists(st.one_of(st.none(), st.floats(0, 1e6, width=32)), min_size=1, max_size=50),
    angle=finite,
    stamp=st.integers(0, 2**62),
)
def test_the_recorded_json_decodes_to_the_same_message(
    ranges: list[float | None], angle: float, stamp: int
) -> None:
    scan = LaserScan(
        stamp_ns=stamp,
        angle_min=angle,
        angle_increment=1e-300 if angle == 0 else angle,
        range_min=0.0,
        range_max=1e7,
        ranges=ranges,
    )
    payload = convert.wire_json(scan)
    assert decode(LaserScan, payload) == scan
    assert convert.wire_json(decode(LaserScan, payload)) == payload
    odom = Odometry(stamp_ns=stamp, x=angle, y=-angle, theta=1e-7 * angle)
    assert decode(Odometry, convert.wire_json(odom)) == odom


@pytest.mark.parametrize(
    "q", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, math.nan, 1.0), (0, 0, 0, math.inf)]
)
def test_a_quaternion_with_no_heading_is_refused_not_taken_as_heading_0(
    q: tuple[float, float, float, float],
) -> None:
    # an orientation left unset is all zeros: it was taken as heading 0 (tf2 refuses it)
    for msg, type_name, read in (
        (initialpose_msg(np.zeros(3), 9), "geometry_msgs/msg/PoseWithCovarianceStamped",
         lambda raw: convert.initial_pose(raw, "m1")),
        (odom_msg(np.zeros(3), 9), "nav_msgs/msg/Odometry", convert.odometry),
    ):  # fmt: skip
        o = msg.pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        raw = bytes(TS.serialize_cdr(msg, type_name))
        with pytest.raises(SchemaError, match=r"orientation: the quaternion .* has no heading"):
            read(raw)
