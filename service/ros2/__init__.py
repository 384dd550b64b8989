"""The ROS 2 front door: ROS 2 robots on rmw_zenoh, and rosbag2 recordings, with no bridge.

A ROS 2 robot that runs rmw_zenoh publishes CDR on rmw_zenoh's own key expressions
(``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<type hash>``); this package reads its ``scan``,
``odom`` (or the ``odom`` -> base transform on ``tf``) and ``initialpose``, turns them into the
WIRE.md messages that the JSON front door gets (so they are recorded, replayed and audited the
same way), and publishes each pose back as Nav2 AMCL does: ``amcl_pose`` and ``map`` -> ``odom``
on the robot's ``tf``, with rmw_zenoh's attachment and liveliness tokens. It also turns rosbag2
recordings into replay inputs and poses into rosbag2 recordings.

Modules: :mod:`~service.ros2.names` (key expressions, liveliness tokens, namespaces to robots),
:mod:`~service.ros2.attachment` (the 33-byte sample attachment), :mod:`~service.ros2.convert`
(CDR to and from WIRE.md messages, with rosbags), :mod:`~service.ros2.frontdoor` (the live
front door on a Zenoh session), :mod:`~service.ros2.roster` (its robots, and their tokens and
publishers), :mod:`~service.ros2.bags` (rosbag2 in and out).

May import: ``rlutf``, ``schemas``, ``service.keys``, ``service.config``, ``service.maps``,
``service.logs`` and ``service.infile``; ``service.live`` and ``service.cli`` import it (the
service wires the front door in), never the other way.
"""
