"""The front door's Zenoh entities as rmw_zenoh declares them, and what it says at start.

Publishers (a transient-local one is an advanced publisher with a cache and a sample-miss
heartbeat, as ``rmw_publisher_data.cpp`` declares it), undeclaring one that may be gone with its
session, the warning of a front door started with no map (:func:`no_map_warning`) and the
Event of a namespace refused, ``max_robots`` held (:func:`limit_message`).
"""

from __future__ import annotations

import logging
from typing import Any

import zenoh
import zenoh.ext

from service.config import Ros2Settings
from service.ros2 import names

log = logging.getLogger(__name__)

#: rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (500 ms, sporadic), seconds.
HEARTBEAT_S = 0.5


def declare_publisher(session: zenoh.Session, key: str, qos: names.Qos) -> Any:
    """A publisher on ``key`` with ``qos`` as rmw_zenoh makes it."""
    common: dict[str, Any] = {
        "congestion_control": zenoh.CongestionControl.DROP,
        "allowed_destination": zenoh.Locality.REMOTE,  # not to our own tf subscriber
    }
    if qos.transient_local:
        # rmw_zenoh's transient-local publisher: a cache late subscribers query; reliable,
        # also sequence numbers and a heartbeat (sent each 0.5 s if a sample went out
        # meanwhile), from which a subscriber with recovery detects a lost last sample and
        # fetches it from the cache (rmw_publisher_data.cpp, Humble to Rolling).
        miss = (
            zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S)
            if qos.reliable
            else None
        )
        return zenoh.ext.declare_advanced_publisher(
            session,
            key,
            cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
            sample_miss_detection=miss,
            publisher_detection=True,
            **common,
        )
    return session.declare_publisher(key, **common)


def undeclare(entity: Any) -> None:
    """Undeclare a publisher, token or subscriber (nothing if it went with the session)."""
    try:
        entity.undeclare()
    except Exception:  # already gone with the session
        log.debug("undeclare failed", exc_info=True)


def no_map_warning(s: Ros2Settings) -> str | None:
    """What goes wrong when ROS robots have no map, and the flag that fixes it (``None``: fine)."""
    if s.map_id is not None:
        return None
    without = "ROS robots" if not s.robots else "ROS robots without ros2.robots.NS.map_id"
    grid = f"; maps on {s.map_topic} will not be imported (they need an id)" if s.map_topic else ""
    service = f" and {s.global_localization_service} calls" if s.global_localization_service else ""
    return (
        f"ROS 2 front door: no map given for {without}: their initial poses (initialpose, "
        f"RViz's 2D Pose Estimate){service} will be refused with an invalid_message Event, "
        f"so they will not be localized{grid}. Fix: rlutf serve --ros2 --ros-map MAP_ID "
        "(or the setting ros2.map_id, or ros2.robots.NS.map_id per robot)"
    )


def limit_message(robot_id: str, max_robots: int, refused: int) -> str:
    """The Event ``robot_limit`` of a namespace the front door refused."""
    return (
        f"ROS robot {robot_id!r} refused: the ROS 2 front door holds {max_robots} robots "
        f"(max_robots); {refused} inputs of new namespaces refused so far. Robots idle for "
        "robot_idle_s make room; raise max_robots or add instances"
    )
