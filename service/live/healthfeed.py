"""Map health in the live service: the workers' evidence merged, published, recorded, answered.

Worker processes count each scan's map health evidence beside the localizer and hand it on
with a batch's outputs at most once a second (``evidence`` outputs,
:class:`service.live.worker.HandOver`). :class:`HealthFeed` merges it into one
:class:`service.maphealth.MapHealthEngine` per service, puts each map's MapHealth on
``{prefix}/maphealth/{map_id}`` when it changed (at most once a second), records it (schema
``rlutf.MapHealth``) and answers gets there. A map version starts its evidence afresh when the
first evidence of it arrives (the map book holds the version the robots are on).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterable

import zenoh

from rlutf.map import Map as World
from schemas import SCHEMA_NAMES, MapHealth
from service.keys import Keys
from service.maphealth import Handed, MapHealthEngine
from service.maps.book import MapBook

MAPHEALTH_SCHEMA = SCHEMA_NAMES[MapHealth]
JSON = zenoh.Encoding.APPLICATION_JSON

Publish = Callable[[str, bytes], None]
Record = Callable[[str, str, bytes, int, int], None]  # key, schema, payload, log time, stamp


class HealthFeed:
    """The service's map health.

    Args:
        keys: the key layout.
        maps: the service's loaded maps.
        publish: puts a payload on a key.
        record: records a message (key, schema, payload, receive time, stamp).
        clock: the service clock, ns.
    """

    def __init__(
        self,
        keys: Keys,
        maps: MapBook,
        publish: Publish,
        record: Record,
        clock: Callable[[], int],
    ) -> None:
        self.keys = keys
        self.maps = maps
        self.publish = publish
        self.record = record
        self.clock = clock
        self.engine = MapHealthEngine(keys)
        self._lock = threading.Lock()

    def on_evidence(self, handed: Iterable[Handed]) -> None:
        """Merge evidence handed on by a worker; put and record what is due."""
        with self._lock:
            for h in handed:
                loaded = self.maps.get(h.map_id)
                known = self.engine.version(h.map_id)
                if loaded is not None and loaded.version == h.version and known != h.version:
                    # With worker processes the map was checked there: built here once a
                    # version, at its first evidence (its walls place the changes).
                    world = loaded.world or World.from_geojson(
                        json.loads(loaded.payload)["geometry"]
                    )
                    self.engine.register_map(h.map_id, h.version, world)
            self.engine.merge(list(handed))
            now = self.clock()
            due = self.engine.due(now)
        for out in due:
            self.publish(out.key, out.payload)
            self.record(out.key, MAPHEALTH_SCHEMA, out.payload, now, out.stamp_ns)

    def on_query(self, query: zenoh.Query) -> None:
        """Answer gets on ``{prefix}/maphealth/*`` with the current MapHealth of each map."""
        with query:
            ke = query.key_expr
            with self._lock:
                answers = [(m, self.engine.answer(m)) for m in self.engine.map_ids()]
            for map_id, payload in answers:
                key = self.keys.maphealth(map_id)
                if payload is not None and ke.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, payload, encoding=JSON)
