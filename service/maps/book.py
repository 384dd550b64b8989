"""Validation and versioning of maps as the service receives them.

One rule decides what a put of a map means, in the store and in every service (WIRE.md v1.2,
:func:`put_verdict`): a newer version replaces the map; the same version with the same content
is an echo and changes nothing; an older version, or the same version with other content, is a
conflict: it changes nothing anywhere and is reported (``map_version_conflict``). Content is
compared on the canonical encoding of the message, so whitespace and key order do not count.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Literal, NamedTuple

from rlutf.errors import MapError
from rlutf.map import Map as World
from rlutf.map import MapLimits
from schemas import Map, SchemaError, decode, encode
from service.maps.helper import IDLE_S, TIMEOUT_S, HelperFailed, HelperProcess

#: Size limit of a map a tool reads from a local file (the service's ``max_map_bytes`` applies
#: when it is put).
FILE_MAX_BYTES = 1 << 31

#: Validations a :class:`MapChecker` remembers.
_CHECKS_KEPT = 4
#: A map payload of at most this many bytes is validated in the service's process even where
#: maps are validated apart: it takes at most a few milliseconds (about 40 us a kB, hostile
#: geometry included: every structure a map's area costs is built later, on use, and bounded
#: by ``max_map_area``), where starting the validating process takes a second and about 57 MB
#: a service process (the simulated fleet's 2 kB map started one in each process of the
#: default layout, 518 MB resident at 200 robots while they ran).
INLINE_BYTES = 64 * 1024

Verdict = Literal["new", "echo", "conflict"]
Held = tuple[int, str]
"""A map version held and the digest of its content (:func:`content_digest`)."""


class MapRejected(ValueError):
    """A map payload that cannot be used; the message says why."""


class VersionConflict(MapRejected):
    """A put of an older version, or of the held version with other content.

    Attributes:
        map_id: the map.
        version: the version put.
        held: the version held.
    """

    def __init__(self, map_id: str, version: int, held: int) -> None:
        self.map_id = map_id
        self.version = version
        self.held = held
        what = "an older version than" if version < held else "other content than"
        super().__init__(
            f"map {map_id!r}: version {version} put, {what} the held version {held}; "
            f"nothing changed (put version {held + 1} or later: rlutf map put --version next)"
        )


def content_digest(msg: Map) -> str:
    """SHA-256 of the message's canonical encoding: equal maps, equal digests."""
    return hashlib.sha256(encode(msg)).hexdigest()


def put_verdict(held: Held | None, version: int, digest: str) -> Verdict:
    """What a put of ``version`` with content ``digest`` means when ``held`` is held."""
    if held is None or version > held[0]:
        return "new"
    if version == held[0] and digest == held[1]:
        return "echo"
    return "conflict"


@dataclass(frozen=True)
class LoadedMap:
    """A validated map version.

    Attributes:
        map_id: its id.
        version: its version.
        payload: the wire payload as received.
        world: the algorithm's map (validated; its index is made where it is first used;
            ``None`` when it was checked in another process, for worker processes that build
            it from the payload).
        received_ns: when the service accepted it.
        digest: :func:`content_digest` of the message.
    """

    map_id: str
    version: int
    payload: bytes
    world: World | None
    received_ns: int
    digest: str = ""


def load_map(
    payload: bytes,
    *,
    expected_id: str | None,
    max_bytes: int,
    limits: MapLimits | None = None,
) -> tuple[Map, World]:
    """Decode and validate a map payload (size, schema, extent and vertex count, geometry).

    Args:
        payload: the Map message.
        expected_id: the id of the key it came on.
        max_bytes: the maps' size limit (``max_map_bytes``), bytes.
        limits: checked on the positions before the geometry is built.

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
        world = World.from_geojson(msg.geometry.model_dump(mode="python"), limits=limits)
    except MapError as err:
        raise MapRejected(f"geometry.{err}") from err
    return msg, world


class CheckedMap(NamedTuple):
    """A valid map payload, without its decoded message (a map of real size is millions of
    Python objects once decoded: kept, they slowed every garbage collection of the process).

    Attributes:
        version: its version.
        digest: :func:`content_digest` of the message.
        world: the algorithm's map (``None`` when it was checked in another process).
    """

    version: int
    digest: str
    world: World | None


def check_map(
    payload: bytes, *, expected_id: str | None, max_bytes: int, limits: MapLimits | None = None
) -> CheckedMap:
    """:func:`load_map`, keeping the version and digest of the message only.

    Raises:
        MapRejected: with a message naming the field and the problem.
    """
    msg, world = load_map(payload, expected_id=expected_id, max_bytes=max_bytes, limits=limits)
    return CheckedMap(msg.version, content_digest(msg), world)


def _check_elsewhere(
    map_id: str, payload: bytes, max_bytes: int, limits: MapLimits | None, keep_world: bool
) -> CheckedMap | str:
    """:func:`check_map` in the validating process, the map itself sent back only with
    ``keep_world`` (its geometry and walls, pickled: :meth:`rlutf.map.Map.__reduce__`); or why
    not."""
    try:
        checked = check_map(payload, expected_id=map_id, max_bytes=max_bytes, limits=limits)
    except MapRejected as err:
        return str(err)
    return checked if keep_world else checked._replace(world=None)


class MapChecker:
    """Validates map payloads (:func:`load_map`) once each: the embedded store and the service's
    map feed see the same put at once, and a map of real size takes seconds to validate.

    Args:
        max_bytes: the maps' size limit, bytes.
        limits: extent and vertex limits of a map.
        isolated: validate in a process of its own (:class:`~service.maps.helper.
            HelperProcess`), which keeps no map: decoding a map holds the interpreter's lock for
            seconds (pydantic and the JSON parser are C code that does not let other threads
            run), which stalled every robot of a service whose Zenoh callbacks share the
            process, and a hostile map costs the process that decodes it a gigabyte. For a
            service whose worker processes build the maps, the main process never needs the
            map itself. The process runs from :meth:`start` or the first map until no map came
            for ``idle_s`` seconds; a map whose validation takes longer than ``timeout_s``, or
            kills the process, is rejected.
        keep_world: with ``isolated``, the validating process sends the map back (its geometry
            and walls, validated; taking them in holds the lock for milliseconds), for a
            service whose robots run in this process; else the map is ``None``.
        idle_s: see ``isolated``.
        timeout_s: see ``isolated``.
        inline_bytes: with ``isolated``, a payload of at most this many bytes is validated in
            this process all the same (:data:`INLINE_BYTES`).
    """

    def __init__(
        self,
        max_bytes: int,
        limits: MapLimits | None = None,
        isolated: bool = False,
        keep_world: bool = False,
        idle_s: float = IDLE_S,
        timeout_s: float = TIMEOUT_S,
        inline_bytes: int = 0,
    ) -> None:
        self.max_bytes = max_bytes
        self.limits = limits
        self.isolated = isolated
        self.inline_bytes = inline_bytes
        self.keep_world = keep_world
        self.process = HelperProcess(_check_elsewhere, "rlutf-mapcheck", idle_s, timeout_s)
        self._lock = threading.Lock()
        self._recent: OrderedDict[tuple[str, bytes], Future[CheckedMap]] = OrderedDict()

    def start(self) -> None:
        """Start the validating process now, if isolated, and wait until it runs (its imports
        take a second or more). A service does not: its first map starts it, so that a service
        with no map to check holds no such process (:data:`service.maps.helper.IDLE_S`)."""
        if self.isolated:
            self.process.start()

    def close(self) -> None:
        """Stop the validating process, if any."""
        self.process.close()

    def _here(self, payload: bytes) -> bool:
        return not self.isolated or len(payload) <= self.inline_bytes

    def _check(self, map_id: str, payload: bytes) -> CheckedMap:
        if self._here(payload):
            checked = check_map(
                payload, expected_id=map_id, max_bytes=self.max_bytes, limits=self.limits
            )
            return checked if not self.isolated or self.keep_world else checked._replace(world=None)
        try:
            found = self.process.call(map_id, payload, self.max_bytes, self.limits, self.keep_world)
        except HelperFailed as err:  # too slow, or killed (out of memory?): a new one next time
            raise MapRejected(f"map {map_id!r}: validating it failed: {err}") from err
        if isinstance(found, str):
            raise MapRejected(found)
        return CheckedMap(*found)

    def build(self, map_id: str, payload: bytes) -> World:
        """The map of a payload already checked, validated: with ``isolated``, by the validating
        process, which sends it back (:meth:`rlutf.map.Map.__reduce__`: taking in a 10 MB map
        holds the lock for about 40 ms at a time, where decoding and validating it here held it
        for up to 0.8 s); else here. Not remembered: the caller keeps it.

        Raises:
            MapRejected: the payload is invalid, or the validating process failed.
        """
        if self._here(payload):
            world = check_map(
                payload, expected_id=map_id, max_bytes=self.max_bytes, limits=self.limits
            ).world
        else:
            try:
                found = self.process.call(map_id, payload, self.max_bytes, self.limits, True)
            except HelperFailed as err:
                raise MapRejected(f"map {map_id!r}: building it failed: {err}") from err
            if isinstance(found, str):
                raise MapRejected(found)
            world = CheckedMap(*found).world
        assert world is not None  # check_map builds it
        return world

    def check(self, map_id: str, payload: bytes) -> CheckedMap:
        """The map's version, digest and map; a second caller with the same payload waits for
        the first one's answer.

        Raises:
            MapRejected: the payload is invalid.
        """
        key = (map_id, hashlib.sha256(payload).digest())
        with self._lock:
            found = self._recent.get(key)
            mine = found is None
            if found is None:
                found = self._recent[key] = Future()
                while len(self._recent) > _CHECKS_KEPT:
                    self._recent.popitem(last=False)
        if mine:
            try:
                found.set_result(self._check(map_id, payload))
            except Exception as err:  # MapRejected, or a bug: the waiters get it too
                found.set_exception(err)
        return found.result()


class MapBook:
    """The newest valid version of every map the service has seen.

    Args:
        max_bytes: the maps' size limit, bytes.
        limits: extent and vertex limits of a map.
        isolated: validate maps in a process of their own (:class:`MapChecker`); the maps
            loaded then carry no :class:`~rlutf.map.Map` unless ``keep_world``.
        keep_world: with ``isolated``, the validating process sends each map back, for a
            service whose robots run in this process.

    A service (:class:`service.live.node.LocalizationService`) validates apart with worker
    processes and in each process of the default layout (``intake`` ``loop``: its one input
    thread also runs its robots, and a validation in-process held the lock from it for up to
    a third of a second at a time, for a 10 MB map); only a service on threads with callback
    intake (the tests' harness) validates in-process.
    """

    def __init__(
        self,
        max_bytes: int,
        limits: MapLimits | None = None,
        isolated: bool = False,
        keep_world: bool = False,
    ) -> None:
        self.checker = MapChecker(
            max_bytes, limits, isolated, keep_world, inline_bytes=INLINE_BYTES
        )
        self._maps: dict[str, LoadedMap] = {}

    def get(self, map_id: str) -> LoadedMap | None:
        """The newest version held, if any."""
        return self._maps.get(map_id)

    def ids(self) -> list[str]:
        """Ids of the maps held."""
        return list(self._maps)

    def offer(
        self, map_id: str, payload: bytes, received_ns: int, store: Held | None = None
    ) -> LoadedMap | None:
        """Take a map payload received on ``{prefix}/maps/{map_id}``.

        ``store``: what the map store holds for the map (its version, or the version removed
        from it), a version to beat as well as the one this book holds, so that the service
        never loads a version the store refused.

        Returns:
            The loaded map when it is new or newer than the one held; ``None`` for an echo of
            the version held.

        Raises:
            VersionConflict: an older version, or the held version with other content.
            MapRejected: the payload is invalid.
        """
        return self.commit(map_id, payload, self.check(map_id, payload), received_ns, store)

    def commit(
        self,
        map_id: str,
        payload: bytes,
        checked: CheckedMap,
        received_ns: int,
        store: Held | None = None,
    ) -> LoadedMap | None:
        """:meth:`offer` of a payload already :meth:`check`-ed (the costly part, which the
        service runs before it takes the dispatcher's lock, as it asks the store for ``store``).

        Raises:
            VersionConflict: an older version, or the held version with other content.
        """
        version, digest, world = checked
        mine = self._maps.get(map_id)
        own = (mine.version, mine.digest) if mine is not None else None
        for held in (store, own):
            if held is not None and put_verdict(held, version, digest) == "conflict":
                raise VersionConflict(map_id, version, held[0])
        if own == (version, digest):
            return None  # an echo of the version held
        loaded = LoadedMap(map_id, version, bytes(payload), world, received_ns, digest)
        self._maps[map_id] = loaded
        return loaded

    def world_of(self, loaded: LoadedMap) -> World:
        """The map of a version held: its own, or, for a map checked in another process and not
        sent back (``isolated`` without ``keep_world``), built by the validating process now
        (:meth:`MapChecker.build`; it may take seconds: call it off the threads that run robots'
        inputs). Not kept in the book: a process that needs no map holds none.

        Raises:
            MapRejected: the validating process failed.
        """
        if loaded.world is not None:
            return loaded.world
        return self.checker.build(loaded.map_id, loaded.payload)

    def check(self, map_id: str, payload: bytes) -> CheckedMap:
        """Validate a payload for ``map_id`` with this book's limits (no state changes).

        Raises:
            MapRejected: the payload is invalid.
        """
        return self.checker.check(map_id, payload)
