"""A map version as the localizers use it, built and indexed by the first update that needs it.

The wall index and the distance field of a map cost time and memory in proportion to its area
and walls (:class:`rlutf.map.MapLimits` bounds both). A worker process is sent every map; it
registers a :class:`PreparedMap` at once, which costs nothing, and the first update of a robot on
that map builds it, on the worker's slow lane (:meth:`service.engine.FleetEngine.
expects_long_update` says so while the map is not ready), so that robots on other maps never
wait for it. A worker whose robots never use a map never builds it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from rlutf.field import distance_field
from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World

WorldSource = World | Callable[[], World]
"""A built map, or how to build it (from its GeoJSON, say)."""


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
        """The map with its wall index (and distance field, when updates search it) made.

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
                if self._config.wide_search and self._config.mode == "default":
                    distance_field(world)
                self._world = world
                self._source = world  # the GeoJSON it was built from can go
            return self._world
