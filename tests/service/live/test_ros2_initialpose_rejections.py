"""A ROS initial pose that is refused is said each time, as a JSON one is.

RViz's "2D Pose Estimate" in the wrong frame, or with a NaN, came right after a malformed
Odometry of the same robot (or within ``event_interval_s`` of any of its rejected inputs): its
Event ``invalid_message`` was held back as one more of the robot's bad inputs, so the operator
heard nothing of why the pose did not take. An initial pose on the JSON key is answered each
time (`rlutf initialpose` waits for it); the ROS 2 front door's now is too.
"""

from __future__ import annotations

from types import SimpleNamespace

from service.config import Settings
from service.live.admission import Gate
from service.live.intake import Intake

ODOM = "0/r1/odom/nav_msgs::msg::dds_::Odometry_/TypeHashNotSupported"
POSE = "0/r1/initialpose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/TypeHashNotSupported"
SCAN = "0/r1/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported"


def _intake(events: list[tuple[str, str, str]]) -> Intake:
    svc = SimpleNamespace(
        settings=Settings(),
        stats=SimpleNamespace(add=lambda name, n=1: None),
        ownership=SimpleNamespace(ready=True, owns=lambda robot: True),
        gate=Gate(lambda: 0, 10**9, 10, event_interval_ns=10**9),
        _robot_event=lambda robot, level, code, about, message, now=None: events.append(
            (robot, about, message)
        ),
    )
    return Intake(svc)  # type: ignore[arg-type]


def test_a_refused_ros_initial_pose_is_said_each_time() -> None:
    events: list[tuple[str, str, str]] = []
    intake = _intake(events)
    t = 10**12
    intake.reject("r1", ODOM, "x: input should be a finite number, got NaN", t)
    intake.reject("r1", POSE, "header.frame_id: the initial pose must be in 'map'", t + 1)
    intake.reject("r1", POSE, "x: input should be a finite number, got NaN", t + 2)
    intake.reject("r1", SCAN, "angle_increment must not be 0", t + 3)  # held back, as before
    assert [(about, message.split(":")[0]) for _, about, message in events] == [
        (ODOM, "x"),
        (POSE, "header.frame_id"),
        (POSE, "x"),
    ]
