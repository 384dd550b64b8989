"""rmw_zenoh key expressions, tokens, QoS strings and the 33-byte attachment."""

from __future__ import annotations

import struct

import pytest
from rosbags.typesys import Stores, get_typestore

from service.ros2 import attachment, names


@pytest.mark.parametrize("store", [Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY, Stores.ROS2_KILTED])
def test_rihs01_hashes_are_rosbags_own(store: Stores) -> None:
    ts = get_typestore(store)
    for msgtype, h in names.RIHS01.items():
        assert ts.hash_rihs01(msgtype) == h


def test_data_keys_of_each_distro_and_their_parsing() -> None:
    jazzy = names.data_key(0, "/robot1/scan", "sensor_msgs/msg/LaserScan", "jazzy")
    assert jazzy == (
        "0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/"
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    )
    humble = names.data_key(7, "/scan", "sensor_msgs/msg/LaserScan", "humble")
    assert humble == "7/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported"
    k = names.parse_data_key(jazzy, 0)
    assert k is not None
    assert (k.topic, k.namespace, k.name, k.msgtype, k.distro) == (
        "/robot1/scan",
        "/robot1",
        "scan",
        "sensor_msgs/msg/LaserScan",
        "jazzy",
    )
    root = names.parse_data_key(humble, 7)
    assert root is not None and (root.namespace, root.distro) == ("/", "humble")
    assert names.parse_data_key(jazzy, 1) is None  # another domain
    assert names.parse_data_key("0/robot1/scan/notatype/x", 0) is None


def test_namespaces_to_robots() -> None:
    assert names.robot_of_namespace("/robot1", "robot") == "robot1"
    assert names.robot_of_namespace("/", "base") == "base"
    assert names.robot_of_namespace("/site/r7", "robot", {"site/r7": "r7"}) == "r7"
    with pytest.raises(names.NamespaceError, match="site/r7"):
        names.robot_of_namespace("/site/r7", "robot")


def test_qos_strings_and_tokens_as_rmw_zenoh_writes_them() -> None:
    # design.md's examples and qos_to_keyexpr: defaults are left empty.
    assert names.Qos().keyexpr() == "::,:,:,:,,"
    assert names.Qos(depth=10).keyexpr() == "::,10:,:,:,,"
    assert names.SENSOR_QOS.keyexpr() == "2::,5:,:,:,,"
    assert names.AMCL_POSE_QOS.keyexpr() == ":1:,1:,:,:,,"
    assert names.node_token(2, "aac3", 0, "listener") == "@ros2_lv/2/aac3/0/0/NN/%/%/listener"
    t = names.entity_token(
        0, "z", 0, 10, "MP", "/robot1/tf", "tf2_msgs/msg/TFMessage", "humble", names.TF_QOS
    )
    assert t == (
        "@ros2_lv/0/z/0/10/MP/%/%/rlutf_localization/%robot1%tf/"
        "tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported/::,100:,:,:,,"
    )
    assert all(t.split("/"))  # rmw_zenoh drops a token with an empty chunk
    assert len(t.split("/")) == 13


def test_attachment_round_trip_and_layout() -> None:
    gid = attachment.gid_of("@ros2_lv/0/z/0/1/MP/x")
    assert len(gid) == 16 and gid == attachment.gid_of("@ros2_lv/0/z/0/1/MP/x")
    seq = attachment.Sequencer(gid)
    a, b = seq.next(111), seq.next(222)
    assert len(a) == 33
    assert struct.unpack_from("<qqB", a) == (1, 111, 16) and a[17:] == gid
    assert attachment.unpack(b) == attachment.Attachment(2, 222, gid)
    assert attachment.unpack(b[:-1]) is None
    assert attachment.unpack(b[:16] + b"\x0f" + b[17:]) is None


def test_service_hashes_are_zenoh_ros2_sdks() -> None:
    from zenoh_ros2_sdk.utils import compute_service_type_hash

    empty = "uint8 structure_needs_at_least_one_member"  # rosidl's member of an empty message
    for srv, h in names.SRV_RIHS01.items():
        assert compute_service_type_hash(srv, empty, empty) == h
