"""The key layout of WIRE.md, the parsing of incoming keys, and the model of each input kind."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

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


#: The Event ``lost`` of a scan with too few returns to compare: no pose goes out for it
#: (:class:`service.engine.FleetEngine`), and the robots view says why (``no_returns``).
NO_RETURNS_MESSAGE = "scan has too few returns to compare; pose kept by odometry"

#: Leaves of a robot key the service itself puts (instances follow each other's poses).
OUTPUT_LEAVES = ("pose", "events")


class KeyError_(ValueError):
    """A key that names an invalid robot or map id."""


class OddKey(NamedTuple):
    """A put or delete on a key no part of the service takes as input (:meth:`Keys.odd`).

    Attributes:
        kind: its class, for rate limiting: ``extra_levels``, ``unknown_leaf``, ``delete``,
            ``map_deleted`` or ``unknown_key``.
        level: of its Event.
        code: of its Event.
        message: of its Event (the key escaped).
    """

    kind: str
    level: Literal["info", "warning", "error"]
    code: str
    message: str


def printable(text: str, limit: int = 200) -> str:
    """``text`` with control and other unprintable characters escaped, at most ``limit`` long.

    For log lines and messages that quote a key a client chose: a newline in a key must not
    forge a line in the service's log.
    """
    if len(text) > limit:
        text = text[:limit] + "..."
    if text.isprintable():
        return text
    return "".join(
        c if c.isprintable() else (f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}")
        for c in text
    )


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

    def map_version(self, map_id: str) -> str:
        """Where the embedded map store answers the version it holds of map ``map_id``, or of
        the one removed from it (:mod:`service.maps.store`)."""
        return f"{self.prefix}/mapversions/{map_id}"

    @property
    def map_versions(self) -> str:
        """Key expression of every map's version in the embedded store."""
        return f"{self.prefix}/mapversions/*"

    def maphealth(self, map_id: str) -> str:
        """Where the MapHealth of map ``map_id`` is put and answered (WIRE.md v1.2)."""
        return f"{self.prefix}/maphealth/{map_id}"

    def mapevidence(self, instance: str) -> str:
        """Where an instance puts the map health evidence it counted (:mod:`service.evidence`)."""
        return f"{self.prefix}/service/{instance}/mapevidence"

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

    def odd(self, key: str, delete: bool) -> OddKey | None:
        """What is wrong with a put (or, with ``delete``, a DELETE) on ``key``, if anything.

        ``None`` for what the service takes or publishes itself: the inputs and outputs of
        robots, maps, Events and MapHealth, and keys outside the prefix. A robot input with an
        invalid id is also ``None`` here: the input subscriber reports it.
        """
        head = f"{self.prefix}/"
        if not key.startswith(head):
            return None
        shown = printable(key)
        parts = key[len(head) :].split("/")
        top, rest = parts[0], parts[1:]
        if top == "robots":
            if delete:
                return OddKey(
                    "delete",
                    "error",
                    "invalid_key",
                    f"DELETE on {shown}: the service takes only puts of inputs; ignored",
                )
            if len(rest) > 2 or len(rest) < 2:
                return OddKey(
                    "extra_levels",
                    "error",
                    "invalid_key",
                    f"key {shown} has {len(rest)} level(s) under {self.prefix}/robots/; inputs "
                    f"are {self.prefix}/robots/{{robot}}/{{{'|'.join(INPUT_KINDS)}}}; ignored",
                )
            leaf = rest[1]
            if leaf in INPUT_KINDS or leaf in OUTPUT_LEAVES:
                return None
            return OddKey(
                "unknown_leaf",
                "error",
                "invalid_key",
                f"key {shown}: {printable(leaf, 64)!r} is not an input "
                f"({', '.join(INPUT_KINDS)}); ignored",
            )
        if top == "maps" and len(rest) == 1:
            if not delete:
                return None  # the map subscriber takes it
            if not valid_id(rest[0]):  # `rlutf/maps/*`, say: no map is removed
                return OddKey(
                    "unknown_key",
                    "error",
                    "invalid_key",
                    f"DELETE on {shown}: {printable(rest[0], 64)!r} is no map id "
                    "([A-Za-z0-9_-]{1,64}); nothing is removed",
                )
            return OddKey(
                "map_deleted",
                "warning",
                "map_deleted",
                f"DELETE on {shown}: the map is removed from the store (if this instance "
                "hosts it); robots localized on it keep the copy they hold",
            )
        if top == "maps":
            return OddKey(
                "extra_levels",
                "error",
                "invalid_key",
                f"key {shown} is not a map key ({self.prefix}/maps/{{map_id}}); ignored",
            )
        if top == "events" and not rest and not delete:
            return None  # the instances' own Events
        if top == "maphealth" and len(rest) == 1 and not delete:
            return None  # another instance's (or process's) MapHealth (WIRE.md v1.2)
        if top == "service" and len(rest) == 2 and rest[1] == "mapevidence" and not delete:
            return None  # an instance's map health evidence (service.evidence)
        return OddKey(
            "unknown_key",
            "error",
            "invalid_key",
            f"{'DELETE on' if delete else 'put on'} {shown}: no part of the service reads "
            "this key; ignored",
        )

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
