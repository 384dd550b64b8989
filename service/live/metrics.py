"""Prometheus metrics of one service instance, served on ``--metrics-port``.

Each instance has a registry of its own (not prometheus_client's global one): tests and
benchmarks run several services in one process, and their figures must not mix.

What the hot path pays (one scan, one pose): one counter increment for the pose's status and
one histogram observation of its latency (fed by :meth:`Stats.latency
<service.live.stats.Stats.latency>`, so there is one call per value for health and metrics),
and one histogram observation per finished batch for the compute time. Everything the service
already counts or holds (messages received and rejected, scans dropped, robots, the recorder
queue) is read when Prometheus scrapes, by :class:`_ServiceCollector`, so there is no second
copy of any counter and nothing to keep in step.

With no port configured the service holds a :class:`NullMetrics`: no registry, no thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from typing import Protocol

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from service.cluster.ownership import Ownership
from service.live.dispatch import Dispatcher
from service.live.httpserve import BoundedServer, serve_metrics
from service.live.robots import RobotView
from service.live.stats import Stats
from service.logs.recording import Recorder

log = logging.getLogger(__name__)

#: Pose statuses of WIRE.md; a counter child for each is made up front (no lookup by label
#: text per pose).
STATUSES = ("tracking", "corrected", "lost")
#: Scan receipt to pose publication, seconds: 1 ms to 1 s.
LATENCY_BUCKETS = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
#: One batch in a worker, seconds; relocalizations run longer than tracking updates.
COMPUTE_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.5, 5.0)

#: Every metric family the endpoint exports (names as they appear in the exposition, counters
#: with their ``_total``; histograms also have ``_bucket``, ``_sum`` and ``_count`` series).
COUNTERS = {
    "rlutf_messages_received_total": "Messages received for robots this instance owns.",
    "rlutf_messages_rejected_total": "Messages rejected as invalid (bad key or payload).",
    "rlutf_scans_dropped_total": "Scans replaced by a newer scan of the robot before processing.",
    "rlutf_scans_skipped_total": "Scans not turned into a pose (too few returns, no map yet).",
    "rlutf_relocalizations_total": "Relocalizations started (Event relocalizing).",
    "rlutf_recorder_overflow_total": "Messages not recorded because the recorder queue was full.",
    "rlutf_recorder_unrecorded_total": "Messages not recorded because the recorder could not "
    "write (a full disk).",
}
GAUGES = {
    "rlutf_robots_held": "Robots with a latest pose held by this instance.",
    "rlutf_robots_owned": "Robots this instance owns (rendezvous hashing over the instances).",
    "rlutf_robots_lost": "Robots held whose latest pose has status lost.",
    "rlutf_recorder_queue_depth": "Messages waiting in the recorder queue.",
    "rlutf_inputs_pending": "Inputs waiting in the robots' mailboxes.",
}
POSES = "rlutf_poses_published_total"
LATENCY = "rlutf_scan_to_pose_latency_seconds"
COMPUTE = "rlutf_worker_compute_seconds"
METRIC_NAMES = frozenset({*COUNTERS, *GAUGES, POSES, LATENCY, COMPUTE})


class Observed(Protocol):
    """What the metrics read from the service at scrape time (a LocalizationService)."""

    @property
    def stats(self) -> Stats:
        """Counters shared with health."""

    @property
    def dispatcher(self) -> Dispatcher:
        """Dropped scans and pending inputs."""

    @property
    def recorder(self) -> Recorder:
        """Queue depth and overflow."""

    @property
    def ownership(self) -> Ownership:
        """Robots owned."""

    @property
    def robot_view(self) -> RobotView:
        """Robots held and lost."""


class Metrics(Protocol):
    """What the service calls; :class:`ServiceMetrics` or :class:`NullMetrics`."""

    @property
    def port(self) -> int | None:
        """The port the endpoint listens on, ``None`` when off."""

    def latency(self, end_to_end_ms: float) -> None:
        """One scan's time from receipt to its pose being published, ms."""

    def compute(self, ms: float) -> None:
        """One batch's compute time in a worker, ms."""

    def pose(self, status: str | None) -> None:
        """One pose published with this status."""

    def start(self, service: Observed) -> None:
        """Read the service's figures at each scrape and start serving."""

    def close(self) -> None:
        """Stop serving."""


class NullMetrics:
    """Metrics off: every call does nothing."""

    @property
    def port(self) -> int | None:
        """Always ``None``."""
        return None

    def latency(self, end_to_end_ms: float) -> None:
        """Nothing."""

    def compute(self, ms: float) -> None:
        """Nothing."""

    def pose(self, status: str | None) -> None:
        """Nothing."""

    def start(self, service: Observed) -> None:
        """Nothing."""

    def close(self) -> None:
        """Nothing."""


class _ServiceCollector(Collector):
    """Reads what the service already counts or holds, at scrape time."""

    def __init__(self, instance: str, service: Observed) -> None:
        self._labels = [instance]
        self._service = service

    def collect(self) -> Iterator[Metric]:
        s = self._service
        stats = s.stats
        counts = {
            "rlutf_messages_received_total": stats.received,
            "rlutf_messages_rejected_total": stats.rejected,
            "rlutf_scans_dropped_total": s.dispatcher.dropped,
            "rlutf_scans_skipped_total": stats.skipped,
            "rlutf_relocalizations_total": stats.relocalizations,
            "rlutf_recorder_overflow_total": s.recorder.overflowed,
            "rlutf_recorder_unrecorded_total": s.recorder.unrecorded,
        }
        for name, value in counts.items():
            family = CounterMetricFamily(
                name.removesuffix("_total"), COUNTERS[name], labels=["instance"]
            )
            family.add_metric(self._labels, value)
            yield family
        owned = s.ownership.figures()["owned_count"]
        levels = {
            "rlutf_robots_held": s.robot_view.held(),
            "rlutf_robots_owned": owned if isinstance(owned, int) else 0,
            "rlutf_robots_lost": s.robot_view.lost(),
            "rlutf_recorder_queue_depth": s.recorder.queued,
            "rlutf_inputs_pending": s.dispatcher.pending(),
        }
        for name, value in levels.items():
            gauge = GaugeMetricFamily(name, GAUGES[name], labels=["instance"])
            gauge.add_metric(self._labels, value)
            yield gauge


class ServiceMetrics:
    """The registry, histograms and endpoint of one instance.

    Args:
        instance: the instance's name, the ``instance`` label of every series.
        port: TCP port of the endpoint (0: any free port; see :attr:`port` once started).
        addr: address to listen on.
    """

    def __init__(self, instance: str, port: int, addr: str = "0.0.0.0") -> None:
        self.instance = instance
        self.registry = CollectorRegistry(auto_describe=False)
        self._want = (addr, port)
        self._server: BoundedServer | None = None
        self._thread: threading.Thread | None = None
        latency = Histogram(
            LATENCY.removesuffix("_seconds"),
            "Scan receipt to pose publication (the pose's end-to-end latency).",
            ["instance"],
            unit="seconds",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        compute = Histogram(
            COMPUTE.removesuffix("_seconds"),
            "Compute time of one batch of a robot's inputs in a worker.",
            ["instance"],
            unit="seconds",
            buckets=COMPUTE_BUCKETS,
            registry=self.registry,
        )
        poses = Counter(
            POSES.removesuffix("_total"),
            "Poses published, by status.",
            ["instance", "status"],
            registry=self.registry,
        )
        # Bound children: per pose, an increment or observation and no label lookup.
        self._latency = latency.labels(instance)
        self._compute = compute.labels(instance)
        self._poses = {status: poses.labels(instance, status) for status in STATUSES}

    @property
    def port(self) -> int | None:
        """The port the endpoint listens on (``None`` until started)."""
        return self._server.server_port if self._server is not None else None

    def latency(self, end_to_end_ms: float) -> None:
        """One scan's time from receipt to its pose being published, ms."""
        self._latency.observe(end_to_end_ms * 1e-3)

    def compute(self, ms: float) -> None:
        """One batch's compute time in a worker, ms."""
        self._compute.observe(ms * 1e-3)

    def pose(self, status: str | None) -> None:
        """One pose published with this status (an unknown status is not counted)."""
        child = self._poses.get(status or "")
        if child is not None:
            child.inc()

    def start(self, service: Observed) -> None:
        """Read ``service``'s figures at each scrape and serve ``/metrics`` on a thread.

        Raises:
            OSError: the address cannot be bound (port in use, address not local).
        """
        self.registry.register(_ServiceCollector(self.instance, service))
        addr, port = self._want
        self._server, self._thread = serve_metrics(port, addr, self.registry)
        log.info("metrics on http://%s:%d/metrics", addr, self._server.server_port)

    def close(self) -> None:
        """Stop the HTTP server and wait for its thread."""
        server, self._server = self._server, None
        if server is None:
            return
        server.shutdown()
        server.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5.0)


def make_metrics(instance: str, port: int | None, addr: str) -> Metrics:
    """:class:`ServiceMetrics` when a port is configured, else :class:`NullMetrics`."""
    if port is None:
        return NullMetrics()
    return ServiceMetrics(instance, port, addr)
