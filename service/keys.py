"""The key layout of WIRE.md, the parsing of incoming keys, and the model of each input kind."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from schemas import InitialPose, LaserScan, Odometry, Relocalize, valid_id

InputKind = Literal["scan", "odom", "initialpose", "relocalize"]
INPUT_KINDS: tuple[InputKind, ...] = ("scan", "odom", "initialpose", "relocalize")
Message = LaserScan | Odometry | InitialPose | Relocalize
MODELS: dict[str, type[Message]] = {
    "scan": LaserScan,
    "odom": Odometry,
    "initialpose": InitialPose,
    "relocalize": Relocalize,
}


class KeyError_(ValueError):
    """A key that names an invalid robot or map id."""


@dataclass(frozen=True)
class Keys:
    """Keys under one prefix (``rlutf`` unless configured)."""

    prefix: str = "rlutf"

    def robot(self, robot: str, leaf: str) -> str:
        """``{prefix}/robots/{robot}/{leaf}``."""
        return f"{self.prefix}/robots/{robot}/{leaf}"

    def pose(self, robot: str) -> str:
        """Where a robot's corrected pose is put and queried."""
        return self.robot(robot, "pose")

    def robot_events(self, robot: str) -> str:
        """Events about one robot."""
        return self.robot(robot, "events")

    @property
    def events(self) -> str:
        """Events not tied to one robot."""
        return f"{self.prefix}/events"

    @property
    def robots_inputs(self) -> str:
        """Key expression of every robot key (inputs and outputs)."""
        return f"{self.prefix}/robots/*/*"

    def robot_leaf(self, leaf: str) -> str:
        """Key expression of one leaf (``scan``, ``pose``, ...) of every robot."""
        return f"{self.prefix}/robots/*/{leaf}"

    @property
    def all_poses(self) -> str:
        """Key expression of every robot's pose."""
        return f"{self.prefix}/robots/*/pose"

    def map(self, map_id: str) -> str:
        """Where map ``map_id`` is stored."""
        return f"{self.prefix}/maps/{map_id}"

    @property
    def maps(self) -> str:
        """Key expression of every map."""
        return f"{self.prefix}/maps/*"

    def maphealth(self, map_id: str) -> str:
        """Where the MapHealth of map ``map_id`` is put and answered (WIRE.md v1.2)."""
        return f"{self.prefix}/maphealth/{map_id}"

    @property
    def all_maphealth(self) -> str:
        """Key expression of every map's MapHealth."""
        return f"{self.prefix}/maphealth/*"

    @property
    def maps_storage(self) -> str:
        """Key expression a map storage declares."""
        return f"{self.prefix}/maps/**"

    def service(self, instance: str) -> str:
        """Liveliness token of an instance."""
        return f"{self.prefix}/service/{instance}"

    def health(self, instance: str) -> str:
        """Health queryable of an instance."""
        return f"{self.prefix}/service/{instance}/health"

    @property
    def all_health(self) -> str:
        """Key expression of every instance's health."""
        return f"{self.prefix}/service/*/health"

    @property
    def all_services(self) -> str:
        """Key expression of every instance's liveliness token."""
        return f"{self.prefix}/service/*"

    def parse_robot_key(self, key: str) -> tuple[str, str] | None:
        """Split ``{prefix}/robots/{robot}/{leaf}`` into ``(robot, leaf)``.

        Returns:
            ``None`` when the key is not a robot key under this prefix.

        Raises:
            KeyError_: the robot id does not match the id pattern.
        """
        head = f"{self.prefix}/robots/"
        if not key.startswith(head):
            return None
        rest = key[len(head) :].split("/")
        if len(rest) != 2:
            return None
        robot, leaf = rest
        if not valid_id(robot):
            raise KeyError_(f"robot id {robot[:80]!r} does not match [A-Za-z0-9_-]{{1,64}}")
        return robot, leaf

    def parse_map_key(self, key: str) -> str | None:
        """The map id of ``{prefix}/maps/{map_id}``; ``None`` for other keys.

        Raises:
            KeyError_: the map id does not match the id pattern.
        """
        head = f"{self.prefix}/maps/"
        if not key.startswith(head):
            return None
        map_id = key[len(head) :]
        if not valid_id(map_id):
            raise KeyError_(f"map id {map_id[:80]!r} does not match [A-Za-z0-9_-]{{1,64}}")
        return map_id
