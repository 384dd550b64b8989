"""Counters and latency percentiles of one instance, for the health queryable."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Protocol

import numpy as np

from schemas import EventCode, Health, LatencyPercentiles

#: Latest latencies kept for the percentiles.
_WINDOW = 10_000
#: Events counted in health, by how their code reads in an encoded Event.
COUNTED_EVENTS = {
    f'"code":"{EventCode.RELOCALIZING}"'.encode(): "relocalizations",
    f'"code":"{EventCode.RELOCALIZED}"'.encode(): "relocalized",
    f'"code":"{EventCode.AMBIGUOUS}"'.encode(): "ambiguous",
}


class Timings(Protocol):
    """Where :class:`Stats` also sends each latency it records (the metrics' histograms)."""

    def latency(self, end_to_end_ms: float) -> None:
        """One scan's time from receipt to its pose being published."""

    def compute(self, ms: float) -> None:
        """One batch's compute time in a worker."""


class _NoTimings:
    def latency(self, end_to_end_ms: float) -> None:
        pass

    def compute(self, ms: float) -> None:
        pass


class Stats:
    """Thread-safe counters of one service instance.

    Args:
        instance: name of the instance.
        timings: also given every latency and compute time recorded (default: nothing).
    """

    def __init__(self, instance: str, timings: Timings | None = None) -> None:
        self.instance = instance
        self.timings: Timings = timings or _NoTimings()
        self.started = time.monotonic()
        self._lock = threading.Lock()
        self.received = 0
        self.rejected = 0
        self.processed = 0
        self.lost = 0
        self.skipped = 0
        self.relocalizations = 0
        self.relocalized = 0
        self.ambiguous = 0
        self._latency_ms: deque[float] = deque(maxlen=_WINDOW)
        self._compute_ms: deque[float] = deque(maxlen=_WINDOW)

    def add(self, name: str, n: int = 1) -> None:
        """Increase a counter."""
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def count_event(self, payload: bytes) -> None:
        """Count an encoded Event of a robot, if it is one of :data:`COUNTED_EVENTS`."""
        for code, counter in COUNTED_EVENTS.items():
            if code in payload:
                self.add(counter)

    def latency(self, end_to_end_ms: float) -> None:
        """Record one scan's time from receipt to its pose being published."""
        with self._lock:
            self._latency_ms.append(end_to_end_ms)
        self.timings.latency(end_to_end_ms)

    def compute(self, ms: float) -> None:
        """Record one batch's compute time in a worker."""
        with self._lock:
            self._compute_ms.append(ms)
        self.timings.compute(ms)

    @staticmethod
    def _percentiles(values: list[float]) -> LatencyPercentiles:
        if not values:
            return LatencyPercentiles()
        p50, p90, p99 = np.percentile(values, [50, 90, 99])
        return LatencyPercentiles(
            p50=float(p50),
            p90=float(p90),
            p99=float(p99),
            max=float(max(values)),
            count=len(values),
        )

    def health(
        self, robots: int, dropped: int, extra: dict[str, object], ready: bool | None = None
    ) -> Health:
        """A Health message of the current figures."""
        with self._lock:
            lat = list(self._latency_ms)
            comp = list(self._compute_ms)
            counts = (self.received, self.rejected, self.processed, self.lost, self.skipped)
            reloc = {
                "relocalizations": self.relocalizations,
                "relocalized": self.relocalized,
                "ambiguous": self.ambiguous,
            }
        compute = self._percentiles(comp)
        return Health(
            instance=self.instance,
            stamp_ns=time.time_ns(),
            uptime_s=time.monotonic() - self.started,
            robots=robots,
            received=counts[0],
            rejected=counts[1],
            processed=counts[2],
            dropped=dropped,
            ready=ready,
            latency_ms=self._percentiles(lat),
            extra={
                "lost": counts[3],
                "scans_not_processed": counts[4],
                "compute_ms": compute.model_dump(),
                **reloc,
                **extra,
            },
        )
