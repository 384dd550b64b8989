"""What the service shows live of what it receives and computes: a protocol and its null object.

With ``foxglove_port`` set, the service holds a :class:`service.live.foxview.FoxgloveView` (a
Foxglove WebSocket server an operator opens in the Foxglove app); otherwise a
:class:`NullLiveView`, so no call site checks whether the view is on. The service hands the view
the same messages it records (:class:`service.logs.recording.Recorder`'s arguments); the view
only keeps the newest one per topic there and does its work on a thread of its own.
"""

from __future__ import annotations

from typing import Any, Protocol

from service.keys import Keys
from service.maps.book import MapBook


class LiveView(Protocol):
    """A live view of the service's inputs, poses and maps."""

    def start(self) -> None:
        """Start serving.

        Raises:
            service.live.foxview.LiveViewError: the port is in use or the address is not
                local.
        """

    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Offer one wire message (the recorder's arguments); never blocks long, never raises."""

    def forget(self, robot: str) -> None:
        """``robot`` is no longer held here (evicted, handed over): stop showing it."""

    @property
    def url(self) -> str | None:
        """Where clients connect (``None`` when off)."""

    def close(self) -> None:
        """Stop serving."""


class NullLiveView:
    """Shows nothing."""

    def start(self) -> None:
        """Nothing to start."""

    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Drop the message."""

    def forget(self, robot: str) -> None:
        """Nothing shown, nothing to forget."""

    @property
    def url(self) -> str | None:
        """Always ``None``."""
        return None

    def close(self) -> None:
        """Nothing to close."""


def make_live_view(settings: Any, maps: MapBook) -> LiveView:
    """The view the settings ask for: a Foxglove server on ``foxglove_port`` or nothing."""
    if settings.foxglove_port is None:
        return NullLiveView()
    from service.live.foxview import FoxgloveView

    return FoxgloveView(
        settings.foxglove_port,
        settings.foxglove_addr,
        maps,
        Keys(settings.prefix),
        rate_hz=settings.foxglove_rate_hz,
        name=f"rlutf {settings.instance}",
    )
