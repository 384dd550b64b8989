"""Where the service records what it receives and sends: a small protocol and its null object.

The MCAP recorder (:mod:`service.logs.mcaplog`) implements :class:`Recorder`; with recording off the
service holds a :class:`NullRecorder`, so no call site checks whether recording is on.
"""

from __future__ import annotations

from typing import Any, Protocol


class Recorder(Protocol):
    """Records wire messages with their topic (the Zenoh key) and times."""

    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Queue one message; never blocks and never raises on a full queue."""

    def set_config(self, config: dict[str, Any]) -> None:
        """Store the effective configuration (MCAP metadata ``rlutf.config``)."""

    @property
    def overflowed(self) -> int:
        """Messages not recorded because the queue was full."""

    @property
    def queued(self) -> int:
        """Messages waiting in the queue to be written (for health and metrics)."""

    @property
    def unrecorded(self) -> int:
        """Messages not recorded because the recorder could not write (a full disk)."""

    def close(self) -> None:
        """Write what is queued and finish the file."""


class NullRecorder:
    """Records nothing."""

    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Drop the message."""

    def set_config(self, config: dict[str, Any]) -> None:
        """Ignore the configuration."""

    @property
    def overflowed(self) -> int:
        """Always 0."""
        return 0

    @property
    def queued(self) -> int:
        """Always 0."""
        return 0

    @property
    def unrecorded(self) -> int:
        """Always 0."""
        return 0

    def close(self) -> None:
        """Nothing to close."""


def make_recorder(settings: Any) -> Recorder:
    """The recorder the settings ask for: MCAP files in ``record_dir`` or nothing."""
    if settings.no_record:
        return NullRecorder()
    from service.logs.mcaplog import McapRecorder

    return McapRecorder(
        settings.record_dir,
        max_bytes=settings.record_max_bytes,
        max_seconds=settings.record_max_seconds,
        queue_size=settings.record_queue,
        instance=settings.instance,
        foxglove=settings.record_views,
    )
