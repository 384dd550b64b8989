"""The MCAP log layout of WIRE.md, and a writer for it.

A log is an MCAP file, chunked and zstd-compressed, whose channels are

* the Zenoh keys of WIRE.md (``rlutf/robots/r1/scan`` ...), message encoding ``json``, schema
  encoding ``jsonschema``, schema names ``rlutf.LaserScan`` etc. with the checked-in JSON Schema
  documents of ``schemas/jsonschema/`` as schema data;
* Foxglove views of the same messages (:mod:`service.logs.foxglove`), schema names ``foxglove.*``
  with Foxglove's published JSON Schemas as schema data, on topics starting ``/foxglove/``.

``log_time`` is when the service received or sent a message, ``publish_time`` its
``stamp_ns``. The effective configuration is MCAP metadata named ``rlutf.config`` whose one key
``json`` holds the configuration as JSON text (MCAP metadata values are strings); a file may
hold several such records, the last one wins.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from functools import cache
from importlib import metadata, resources
from typing import IO, Any, NamedTuple

from mcap.writer import CompressionType, Writer

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


@cache
def schema_data(schema_name: str) -> bytes | None:
    """The JSON Schema document logged for a schema name, or ``None`` if none is known.

    ``rlutf.*`` documents are the checked-in files of ``schemas/jsonschema/``; ``foxglove.*``
    ones are Foxglove's published schemas embedded under ``service/logs/foxglove_schemas/``.
    """
    if schema_name.startswith("rlutf."):
        path = resources.files("schemas").joinpath("jsonschema", f"{schema_name}.json")
    elif schema_name.startswith("foxglove."):
        path = resources.files("service.logs").joinpath("foxglove_schemas", f"{schema_name}.json")
    else:
        return None
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


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
    except json.JSONDecodeError:
        return None
    return value if isinstance(value, dict) else None


class LogWriter:
    """Writes one log file: channels and schemas are registered on first use.

    Not thread-safe (neither is :class:`mcap.writer.Writer`): one thread owns it.

    Args:
        output: a binary stream; the caller closes it after :meth:`finish`.
        converter: called with every written record; what it returns is written too.
        chunk_size: uncompressed chunk size, bytes, at which a chunk is closed.
    """

    def __init__(
        self,
        output: IO[bytes],
        converter: Converter | None = None,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ) -> None:
        self._writer = Writer(output, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=LIBRARY)
        self._converter = converter
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self.messages = 0
        self.dirty = False

    def _channel(self, topic: str, schema_name: str) -> int:
        key = (topic, schema_name)
        channel = self._channels.get(key)
        if channel is not None:
            return channel
        schema_id = self._schemas.get(schema_name)
        if schema_id is None:
            data = schema_data(schema_name)
            schema_id = 0
            if data is not None:
                schema_id = self._writer.register_schema(schema_name, SCHEMA_ENCODING, data)
            self._schemas[schema_name] = schema_id
        channel = self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id)
        self._channels[key] = channel
        return channel

    def write(self, record: Record) -> None:
        """Write one message, then whatever the converter makes of it."""
        self._add(record)
        if self._converter is not None:
            for extra in self._converter(record):
                self._add(extra)

    def write_all(self, records: Iterable[Record]) -> None:
        """Write several messages."""
        for record in records:
            self.write(record)

    def _add(self, record: Record) -> None:
        channel = self._channel(record.topic, record.schema_name)
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        self._writer.add_message(
            channel_id=channel,
            log_time=record.log_time_ns,
            data=record.payload,
            publish_time=record.publish_time_ns,
            sequence=sequence % 2**32,
        )
        self.messages += 1
        self.dirty = True

    def write_config(self, config: Mapping[str, Any]) -> None:
        """Store the effective configuration as ``rlutf.config`` metadata."""
        self.write_metadata(CONFIG_METADATA, config_metadata(config))

    def write_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Store one metadata record."""
        self._writer.add_metadata(name, dict(data))
        self.dirty = True

    def flush(self) -> None:
        """Close the open chunk and push everything to the stream (no fsync)."""
        self._writer.flush()
        self.dirty = False

    def finish(self) -> None:
        """Write the summary and footer; the file is complete."""
        self._writer.finish()
        self.dirty = False
