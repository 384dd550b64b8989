"""The MCAP log layout of WIRE.md, and a writer for it.

A log is an MCAP file, chunked and zstd-compressed, whose channels are

* the Zenoh keys of WIRE.md (``rlutf/robots/r1/scan`` ...), message encoding ``json``, schema
  encoding ``jsonschema``, schema names ``rlutf.LaserScan`` etc. with the checked-in JSON Schema
  documents of ``schemas/jsonschema/`` as schema data;
* optionally, Foxglove views of the same messages (:mod:`service.logs.foxglove`), schema names
  ``foxglove.*`` with Foxglove's published JSON Schemas as schema data, on topics starting
  ``/foxglove/`` (written by replay and ``rlutf log views``; live only with ``record_views``).

``log_time`` is when the service received or sent a message, ``publish_time`` its
``stamp_ns``. The effective configuration is MCAP metadata named ``rlutf.config`` whose one key
``json`` holds the configuration as JSON text (MCAP metadata values are strings); a file may
hold several such records, the last one wins.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from importlib import metadata, resources
from importlib.resources.abc import Traversable
from typing import IO, Any, NamedTuple

from schemas import SCHEMA_NAMES
from service.logs.manifest import MANIFEST_METADATA, Manifest
from service.logs.mcapwriter import McapWriter

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
CONFIG_METADATA = "rlutf.config"
"""Name of the metadata record holding the effective configuration."""
CONFIG_KEY = "json"
"""Key of the configuration's JSON text inside the ``rlutf.config`` metadata record."""


def _library() -> str:
    """What writes the logs: ``rlutf`` and the package version, so that an auditor can tell
    which code recorded a log (a change to the localizer's results changes the version)."""
    try:
        return f"rlutf {metadata.version('rlutf')}"
    except metadata.PackageNotFoundError:  # run from a source tree that is not installed
        return "rlutf"


LIBRARY = _library()
DEFAULT_CHUNK_SIZE = 1024 * 1024
#: zstd level of the chunks: see BENCHMARKS.md ("The recorder's cost per scan").
DEFAULT_ZSTD_LEVEL = 1


class Record(NamedTuple):
    """One message as it is logged.

    Attributes:
        topic: the channel topic (a Zenoh key, or a ``/foxglove/...`` topic).
        schema_name: e.g. ``rlutf.LaserScan``.
        payload: the JSON payload, UTF-8.
        log_time_ns: when the service received or sent it, ns since the epoch.
        publish_time_ns: the message's own stamp, ns since the epoch.
    """

    topic: str
    schema_name: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int


Converter = Callable[[Record], list[Record]]
"""Turns a logged message into further messages to log beside it (the Foxglove views)."""


#: The Foxglove views' schema names: :data:`service.logs.foxglove.SCHEMA_NAMES` (which imports
#: this module; a test keeps the two the same).
VIEW_SCHEMA_NAMES = (
    "foxglove.LaserScan",
    "foxglove.PoseInFrame",
    "foxglove.FrameTransform",
    "foxglove.SceneUpdate",
)


class SchemaMissing(Exception):
    """A schema a log may name has no document in the installed package.

    Args:
        schema_name: e.g. ``rlutf.LaserScan``.
        where: the file that was looked for, or why none is known.
    """

    def __init__(self, schema_name: str, where: str) -> None:
        super().__init__(
            f"no JSON Schema for {schema_name} ({where}): the installed rlutf package is "
            "incomplete or was changed under the service; reinstall it "
            "(pip install --force-reinstall) and start again"
        )
        self.schema_name = schema_name


def _schema_file(schema_name: str) -> Traversable | None:
    """Where the installed package keeps a schema name's document; ``None`` if nowhere."""
    if schema_name.startswith("rlutf."):
        return resources.files("schemas").joinpath("jsonschema", f"{schema_name}.json")
    if schema_name.startswith("foxglove."):
        return resources.files("service.logs").joinpath("foxglove_schemas", f"{schema_name}.json")
    return None


def schema_data(schema_name: str) -> bytes | None:
    """The JSON Schema document logged for a schema name, read now; ``None`` if none is known.

    ``rlutf.*`` documents are the checked-in files of ``schemas/jsonschema/``; ``foxglove.*``
    ones are Foxglove's published schemas embedded under ``service/logs/foxglove_schemas/``.
    """
    path = _schema_file(schema_name)
    if path is None:
        return None
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


def load_schemas() -> dict[str, bytes]:
    """Every schema a log may name (WIRE.md's and the Foxglove views'), read now.

    A writer holds them from its creation on: before, each was read from the installed package
    when a channel was first used, and a ``pip install`` under a running service (or a file
    removed) made the next new channel's schema id 0, silently, and the log unauditable.

    Raises:
        SchemaMissing: one of them cannot be read.
    """
    found: dict[str, bytes] = {}
    for name in (*sorted(SCHEMA_NAMES.values()), *VIEW_SCHEMA_NAMES):
        path = _schema_file(name)
        try:
            found[name] = path.read_bytes() if path is not None else b""
        except OSError as err:
            raise SchemaMissing(name, f"{path}: {err.strerror or err}") from err
        if not found[name]:
            raise SchemaMissing(name, f"{path}: empty")
    return found


def config_metadata(config: Mapping[str, Any]) -> dict[str, str]:
    """The ``rlutf.config`` metadata record's data for a configuration."""
    return {CONFIG_KEY: json.dumps(config, sort_keys=True, separators=(",", ":"))}


def config_from_metadata(data: Mapping[str, str]) -> dict[str, Any] | None:
    """The configuration stored in an ``rlutf.config`` record; ``None`` if unreadable."""
    text = data.get(CONFIG_KEY)
    if text is None:
        return None
    try:
        value = json.loads(text)
    except (json.JSONDecodeError, RecursionError):
        return None
    return value if isinstance(value, dict) else None


class LogWriter:
    """Writes one log file: channels and schemas are registered on first use.

    Not thread-safe: one thread owns it. The file is written by :class:`McapWriter`, the same
    bytes as ``mcap.writer.Writer`` with the same zstd level.

    Args:
        output: a binary stream; the caller closes it after :meth:`finish`.
        converter: called with every written record; what it returns is written too.
        chunk_size: uncompressed chunk size, bytes, at which a chunk is closed.
        zstd_level: the chunks' zstd level.
        schemas: schema data to log for these schema names instead of the package's own
            (a copy of a log keeps the log's own).
        known: the package's schemas, as :func:`load_schemas` read them (a recorder reads them
            once for all its files); read now when not given.

    Raises:
        SchemaMissing: ``known`` is not given and a schema cannot be read.
    """

    def __init__(
        self,
        output: IO[bytes],
        converter: Converter | None = None,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        zstd_level: int = DEFAULT_ZSTD_LEVEL,
        schemas: Mapping[str, bytes] | None = None,
        known: Mapping[str, bytes] | None = None,
    ) -> None:
        book = dict(load_schemas() if known is None else known)
        book.update((name, data) for name, data in (schemas or {}).items() if data)
        self._book = book
        self._writer = McapWriter(output, chunk_size, zstd_level)
        self._writer.start(profile="", library=LIBRARY)
        self._converter = converter
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self.dirty = False

    @property
    def messages(self) -> int:
        """Messages written."""
        return sum(self._writer.counts.values())

    def counts(self) -> dict[tuple[str, str], int]:
        """Messages written per topic and schema name."""
        written = self._writer.counts
        return {key: written.get(channel, 0) for key, channel in self._channels.items()}

    def _channel(self, topic: str, schema_name: str) -> int:
        key = (topic, schema_name)
        channel = self._channels.get(key)
        if channel is not None:
            return channel
        schema_id = self._schemas.get(schema_name)
        if schema_id is None:
            data = self._book.get(schema_name)
            if data is None:  # a channel without a schema is a log no audit can read
                raise SchemaMissing(schema_name, "not a schema of WIRE.md or of the views")
            schema_id = self._writer.register_schema(schema_name, SCHEMA_ENCODING, data)
            self._schemas[schema_name] = schema_id
        channel = self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id)
        self._channels[key] = channel
        return channel

    def write(self, record: Record) -> None:
        """Write one message, then whatever the converter makes of it."""
        self.add(*record)
        if self._converter is not None:
            for extra in self._converter(record):
                self.add(*extra)

    def write_all(self, records: Iterable[Record]) -> None:
        """Write several messages."""
        for record in records:
            self.write(record)

    def add(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Write one message, and nothing made of it (the converter is not called)."""
        channel = self._channels.get((topic, schema_name)) or self._channel(topic, schema_name)
        self._writer.add_message(channel, log_time_ns, payload, publish_time_ns)
        self.dirty = True

    @property
    def converts(self) -> bool:
        """Whether written messages go through a converter."""
        return self._converter is not None

    def write_config(self, config: Mapping[str, Any]) -> None:
        """Store the effective configuration as ``rlutf.config`` metadata."""
        self.write_metadata(CONFIG_METADATA, config_metadata(config))

    def write_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Store one metadata record."""
        self._writer.add_metadata(name, dict(data))
        self.dirty = True

    def write_manifest(self, run_id: str, sequence: int, last: bool) -> None:
        """Close the open chunk, then store the ``rlutf.manifest`` of everything written (see
        :mod:`service.logs.manifest`): the last record before :meth:`finish`, so that a file
        cut short before its end has none rather than one that lists messages it lost."""
        self.flush()
        manifest = Manifest.of(self, run_id, sequence, last)
        self.write_metadata(MANIFEST_METADATA, manifest.to_metadata())

    def flush(self) -> None:
        """Close the open chunk and push everything to the stream (no fsync)."""
        self._writer.flush()
        self.dirty = False

    def finish(self) -> None:
        """Write the summary and footer; the file is complete."""
        self._writer.finish()
        self.dirty = False
