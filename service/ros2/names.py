"""rmw_zenoh's names: data key expressions, liveliness tokens, QoS strings, namespaces to robots.

Read in rmw_zenoh's sources (``liveliness_utils.cpp``: ``TopicInfo``, ``Entity``,
``qos_to_keyexpr``; ``rmw_publisher_data.cpp`` for the type hash of each distribution):

- data: ``<domain>/<topic without its leading slash>/<pkg>::msg::dds_::<Type>_/<type hash>``;
- the type hash is ``RIHS01_<64 hex>`` from Jazzy on, the literal ``TypeHashNotSupported`` in
  Humble, so a Humble robot and a Jazzy robot never match on one key;
- tokens: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/
  <node>[/<topic>/<type>/<hash>/<qos>]``, every ``/`` inside a name mangled to ``%``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from schemas import valid_id

Distro = Literal["humble", "jazzy"]
"""How a robot's rmw_zenoh names types: ``humble`` (no hash) or ``jazzy`` (Jazzy and later)."""

HUMBLE_HASH = "TypeHashNotSupported"

#: RIHS01 hashes of the types the front door uses (rosbags' ``hash_rihs01``; identical in the
#: Humble, Jazzy, Kilted and Rolling type stores, and checked against public ``ros2 topic info``
#: output).
RIHS01: dict[str, str] = {
    "sensor_msgs/msg/LaserScan": (
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    ),
    "nav_msgs/msg/Odometry": (
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
    ),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
    ),
    "tf2_msgs/msg/TFMessage": (
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    ),
    "diagnostic_msgs/msg/DiagnosticArray": (
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e"
    ),
}
#: Services: a service's hash covers its request, response and event types (rosbags has no
#: services; zenoh-ros2-sdk's ``compute_service_type_hash`` gives it, and ROS 2's docs show the
#: same in ``ros2 service info /clear``).
SRV_RIHS01: dict[str, str] = {
    "std_srvs/srv/Empty": (
        "RIHS01_5888399dedec5ccc85ea6451949fd2c9f97bfdf963f9a588821639fcd31b5d19"
    ),
}

_DDS_TYPE = re.compile(r"^([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_$")


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/LaserScan`` -> ``sensor_msgs::msg::dds_::LaserScan_``."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str | None:
    """``sensor_msgs::msg::dds_::LaserScan_`` -> ``sensor_msgs/msg/LaserScan``; else ``None``."""
    m = _DDS_TYPE.match(dds)
    return f"{m[1]}/{m[2]}/{m[3]}" if m else None


def type_hash(msgtype: str, distro: Distro) -> str:
    """The hash chunk a robot of ``distro`` uses for ``msgtype``."""
    if distro == "humble":
        return HUMBLE_HASH
    return RIHS01[msgtype] if "/msg/" in msgtype else SRV_RIHS01[msgtype]


def distro_of_hash(chunk: str) -> Distro:
    """The distribution that writes this hash chunk."""
    return "humble" if chunk == HUMBLE_HASH else "jazzy"


def data_key(domain: int, topic: str, msgtype: str, distro: Distro) -> str:
    """The key expression rmw_zenoh puts ``msgtype`` on for the fully qualified ``topic``."""
    return f"{domain}/{topic.strip('/')}/{dds_type(msgtype)}/{type_hash(msgtype, distro)}"


def subscription_key(domain: int, name: str) -> str:
    """Every data key of a topic called ``name`` in any namespace, any type and hash."""
    return f"{domain}/**/{name.strip('/')}/*/*"


@dataclass(frozen=True)
class DataKey:
    """A parsed rmw_zenoh data key.

    Attributes:
        topic: the fully qualified topic, ``/robot1/scan``.
        namespace: the topic's namespace, ``/robot1`` (``/`` for none).
        name: the topic's last name, ``scan``.
        msgtype: the ROS type, ``sensor_msgs/msg/LaserScan``.
        distro: which naming of the type hash the publisher uses.
    """

    topic: str
    namespace: str
    name: str
    msgtype: str
    distro: Distro


def parse_data_key(key: str, domain: int) -> DataKey | None:
    """Split a data key of ``domain``; ``None`` when it is not one (other tools' keys)."""
    parts = key.split("/")
    if len(parts) < 4 or parts[0] != str(domain):
        return None
    msgtype = ros_type(parts[-2])
    if msgtype is None:
        return None
    names = parts[1:-2]
    namespace = "/" + "/".join(names[:-1])
    return DataKey("/" + "/".join(names), namespace, names[-1], msgtype, distro_of_hash(parts[-1]))


def join_topic(namespace: str, name: str) -> str:
    """``/robot1`` + ``scan`` -> ``/robot1/scan``; the root namespace gives ``/scan``."""
    ns = namespace.strip("/")
    return f"/{ns}/{name.strip('/')}" if ns else f"/{name.strip('/')}"


class NamespaceError(ValueError):
    """A namespace that does not name a robot."""


def robot_of_namespace(
    namespace: str, root_robot: str, overrides: dict[str, str] | None = None
) -> str:
    """The robot id of a namespace: ``/robot1`` is ``robot1``; ``/`` is ``root_robot``.

    Args:
        namespace: ``/robot1``, ``/`` or a nested ``/site/robot1``.
        root_robot: the id of a robot with no namespace.
        overrides: namespace (without slashes) to robot id, from the settings.

    Raises:
        NamespaceError: the namespace is not a valid robot id and no override names it.
    """
    ns = namespace.strip("/")
    if overrides and ns in overrides:
        return overrides[ns]
    if not ns:
        return root_robot
    if not valid_id(ns):
        raise NamespaceError(
            f"namespace {namespace[:80]!r} is not a robot id ([A-Za-z0-9_-]{{1,64}}); "
            "give it one in the settings (ros2.robots)"
        )
    return ns


# ------------------------------------------------------------------------ liveliness tokens
def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: ``/`` becomes ``%`` (``/`` alone gives ``%``)."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Qos:
    """The QoS a token announces (rmw_zenoh's defaults: reliable, volatile, keep last 42)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 42

    def keyexpr(self) -> str:
        """``qos_to_keyexpr``: fields equal to the defaults are left empty."""
        rel = "" if self.reliable else "2"
        dur = "1" if self.transient_local else ""
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{rel}:{dur}:,{depth}:,:,:,,"


#: QoS of each topic, as Nav2 AMCL, tf2 and the drivers use them.
SENSOR_QOS = Qos(reliable=False, depth=5)
AMCL_POSE_QOS = Qos(transient_local=True, depth=1)
TF_QOS = Qos(depth=100)
INITIALPOSE_QOS = Qos(depth=5)
ODOM_QOS = Qos(depth=10)
MAP_QOS = Qos(transient_local=True, depth=1)
DIAGNOSTICS_QOS = Qos(depth=10)

NODE_NAME = "rlutf_localization"


def node_token(domain: int, zid: str, node_id: int, name: str = NODE_NAME) -> str:
    """The ``NN`` token of a node in the root namespace and enclave."""
    return f"@ros2_lv/{domain}/{zid}/{node_id}/{node_id}/NN/%/%/{mangle(name)}"


def entity_token(
    domain: int,
    zid: str,
    node_id: int,
    entity_id: int,
    kind: Literal["MP", "MS", "SS"],
    topic: str,
    msgtype: str,
    distro: Distro,
    qos: Qos,
    name: str = NODE_NAME,
) -> str:
    """The ``MP`` (publisher), ``MS`` (subscription) or ``SS`` (service) token of the node."""
    return (
        f"@ros2_lv/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/%/{mangle(name)}/"
        f"{mangle(topic)}/{dds_type(msgtype)}/{type_hash(msgtype, distro)}/{qos.keyexpr()}"
    )
