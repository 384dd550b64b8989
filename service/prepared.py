"""A map version as the localizers use it, built and indexed by the first update that needs it.

The wall index and the distance field of a map cost time and memory in proportion to its area
and walls (:class:`rlutf.map.MapLimits` bounds both). A worker process is sent every map; it
registers a :class:`PreparedMap` at once, which costs nothing, and the first update of a robot on
that map builds it, on the worker's slow lane (:meth:`service.engine.FleetEngine.
expects_long_update` says so while the map is not ready), so that robots on other maps never
wait for it. A worker whose robots never use a map never builds it. :class:`MapShelf` holds an
engine's map versions by the time they were received.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from rlutf.field import distance_field
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World
from rlutf.map import coarse_map

WorldSource = World | Callable[[], World]
"""A built map, or how to build it (from its GeoJSON, say)."""

#: Versions of one map kept for inputs that were received before a newer version.
_MAP_VERSIONS_KEPT = 3


class PreparedMap:
    """One map version, made ready once, whichever thread asks first.

    Args:
        source: the map or a function that builds it.
        config: the localizer's parameters (whether its updates search the distance field).
    """

    def __init__(self, source: WorldSource, config: LocalizerConfig) -> None:
        self._source = source
        self._config = config
        self._world: World | None = None
        self._lock = threading.Lock()

    @property
    def ready(self) -> bool:
        """Whether :meth:`world` returns without building anything."""
        return self._world is not None

    def world(self) -> World:
        """The map with its wall index (and distance field, when updates search it, and the
        simplified walls a traced map is tracked on) made.

        Threads that ask while another builds it wait for that one (each structure is made
        once); the first caller pays.
        """
        found = self._world
        if found is not None:
            return found
        with self._lock:
            if self._world is None:
                source = self._source
                world = source if isinstance(source, World) else source()
                world.index  # noqa: B018 (made now, not in the middle of a ray cast)
                cfg = self._config
                if cfg.wide_search and cfg.mode == "default":
                    distance_field(world)
                if cfg.refine and cfg.mode == "default":
                    # The simplified walls a traced map is tracked on (the map itself if drawn).
                    coarse_map(world, cfg.coarse_tolerance).index  # noqa: B018
                self._world = world
                self._source = world  # the GeoJSON it was built from can go
            return self._world


@dataclass
class _Versions:
    received: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    maps: list[PreparedMap] = field(default_factory=list)


class MapShelf:
    """The map versions an engine holds, each made ready by its first user; thread-safe.

    Args:
        config: the localizer's parameters (what a map is prepared with).
    """

    def __init__(self, config: LocalizerConfig) -> None:
        self._config = config
        self._maps: dict[str, _Versions] = {}
        self._lock = threading.Lock()

    def register(self, map_id: str, version: int, source: WorldSource, received_ns: int) -> None:
        """Make a version available from ``received_ns`` on (older versions are ignored)."""
        prepared = PreparedMap(source, self._config)
        with self._lock:
            book = self._maps.setdefault(map_id, _Versions())
            if book.versions and version <= book.versions[-1]:
                return
            book.received.append(received_ns)
            book.versions.append(version)
            book.maps.append(prepared)
            if len(book.maps) > _MAP_VERSIONS_KEPT:
                del book.received[0], book.versions[0], book.maps[0]

    def at(self, map_id: str, received_ns: int) -> tuple[int, World] | None:
        """The version current at ``received_ns`` and its map, built now if it was not."""
        with self._lock:
            book = self._maps.get(map_id)
            i = bisect.bisect_right(book.received, received_ns) - 1 if book else -1
            if book is None or i < 0:
                return None
            version, prepared = book.versions[i], book.maps[i]
        return version, prepared.world()  # outside the lock: it may take a while

    def unready(self, map_id: str) -> bool:
        """Whether the newest version of a map is registered but not built yet."""
        with self._lock:
            book = self._maps.get(map_id)
            return book is not None and not book.maps[-1].ready
