"""Validation and versioning of maps as the service receives them."""

from __future__ import annotations

from dataclasses import dataclass

from rlutf.errors import MapError
from rlutf.map import Map as World
from schemas import Map, SchemaError, decode


class MapRejected(ValueError):
    """A map payload that cannot be used; the message says why."""


@dataclass(frozen=True)
class LoadedMap:
    """A validated map version.

    Attributes:
        map_id: its id.
        version: its version.
        payload: the wire payload as received.
        world: the algorithm's map.
        received_ns: when the service accepted it.
    """

    map_id: str
    version: int
    payload: bytes
    world: World
    received_ns: int


def load_map(payload: bytes, *, expected_id: str | None, max_bytes: int) -> tuple[Map, World]:
    """Decode and validate a map payload (schema, then geometry).

    Raises:
        MapRejected: with a message naming the field and the problem.
    """
    try:
        msg = decode(Map, payload, max_bytes=max_bytes)
    except SchemaError as err:
        raise MapRejected(str(err)) from err
    if expected_id is not None and msg.map_id != expected_id:
        raise MapRejected(f"map_id: {msg.map_id!r} does not match the key's id {expected_id!r}")
    try:
        world = World.from_geojson(msg.geometry.model_dump(mode="python"))
    except MapError as err:
        raise MapRejected(f"geometry.{err}") from err
    return msg, world


class MapBook:
    """The newest valid version of every map the service has seen."""

    def __init__(self, max_bytes: int) -> None:
        self._max_bytes = max_bytes
        self._maps: dict[str, LoadedMap] = {}

    def get(self, map_id: str) -> LoadedMap | None:
        """The newest version held, if any."""
        return self._maps.get(map_id)

    def ids(self) -> list[str]:
        """Ids of the maps held."""
        return list(self._maps)

    def offer(self, map_id: str, payload: bytes, received_ns: int) -> LoadedMap | None:
        """Take a map payload received on ``{prefix}/maps/{map_id}``.

        Returns:
            The loaded map when it is new or newer than the one held; ``None`` when it is not
            newer (an echo or an old version).

        Raises:
            MapRejected: the payload is invalid.
        """
        msg, world = load_map(payload, expected_id=map_id, max_bytes=self._max_bytes)
        held = self._maps.get(map_id)
        if held is not None and msg.version <= held.version:
            return None
        loaded = LoadedMap(map_id, msg.version, bytes(payload), world, received_ns)
        self._maps[map_id] = loaded
        return loaded
