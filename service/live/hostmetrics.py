"""The metrics endpoint of a host of service processes (:mod:`service.live.host`).

Each process serves its own metrics (:mod:`service.live.metrics`) on a loopback port the host
chose; every series there carries the process's name as its ``instance`` label. The host's
endpoint, on ``--metrics-port``, reads them all at each scrape and serves them as one
exposition, a metric family holding every process's series: one target for Prometheus, and
the same names and labels as a single process's endpoint. A process that does not answer (it
is starting again) is left out of that scrape, and ``rlutf_host_processes_scraped`` says how
many answered.
"""

from __future__ import annotations

import logging
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

from prometheus_client import CollectorRegistry
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.parser import text_string_to_metric_families

from service.live.httpserve import BoundedServer, serve_metrics

log = logging.getLogger(__name__)

#: Seconds the host waits for one process's metrics.
SCRAPE_TIMEOUT_S = 2.0


def _fetch(port: int) -> str | None:
    """The exposition of the process on ``port``, or ``None`` if it does not answer in time."""
    try:
        url = f"http://127.0.0.1:{port}/metrics"
        with urllib.request.urlopen(url, timeout=SCRAPE_TIMEOUT_S) as reply:
            return str(reply.read().decode())
    except OSError as err:
        log.debug("metrics of the process on port %d: %s", port, err)
        return None


class _Merged:
    """A collector: the processes' families, merged by name (in the processes' order).

    The processes are read at once, each on a thread of its own: read in turn, a process that
    hung (stopped, or its GIL held) cost the scrape its whole timeout each, and a scrape of a
    few such processes outlasted Prometheus's own timeout (10 s by default), which then saw
    nothing of the processes that did answer.
    """

    def __init__(self, ports: list[int]) -> None:
        self._ports = ports

    def collect(self) -> Iterator[Metric]:
        merged: dict[str, Metric] = {}
        answered = 0
        with ThreadPoolExecutor(max_workers=max(len(self._ports), 1)) as pool:
            texts = list(pool.map(_fetch, self._ports))
        for text in texts:
            if text is None:
                continue
            answered += 1
            for family in text_string_to_metric_families(text):
                held = merged.get(family.name)
                if held is None:
                    merged[family.name] = family
                else:
                    held.samples.extend(family.samples)
        yield from merged.values()
        scraped = GaugeMetricFamily(
            "rlutf_host_processes_scraped", "Service processes whose metrics this scrape read."
        )
        scraped.add_metric([], answered)
        yield scraped


class HostMetrics:
    """The host's endpoint on ``port`` (0: any free one), merging the processes' ``ports``."""

    def __init__(self, ports: list[int], port: int, addr: str = "0.0.0.0") -> None:
        self._ports = ports
        self._want = (port, addr)
        self.registry = CollectorRegistry(auto_describe=False)
        self._server: BoundedServer | None = None
        self.port: int | None = None

    def start(self) -> None:
        """Serve (raises OSError when the port is taken)."""
        self.registry.register(_Merged(self._ports))
        port, addr = self._want
        server, _thread = serve_metrics(port, addr, self.registry)
        self._server = server
        self.port = int(server.server_address[1])

    def close(self) -> None:
        """Stop serving."""
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
