"""The Prometheus endpoint of a real service on loopback, scraped over HTTP."""

from __future__ import annotations

import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families
from service_harness import JSON, Bench, Collector, running_bench

from service.live.metrics import METRIC_NAMES, NullMetrics, ServiceMetrics
from service.live.sessions import free_port

pytestmark = pytest.mark.integration

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def scrape(port: int) -> Samples:
    """Every sample of ``http://127.0.0.1:port/metrics`` by (name, labels)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        assert reply.status == 200
        text = reply.read().decode()
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def value(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, frozenset(labels.items()))]


def _feed(bench: Bench, steps: int) -> Collector:
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/*/pose", col)
    bench.put_map()
    time.sleep(0.3)
    robot = bench.robot("r1", 1)
    robot.initial_pose("m1")
    time.sleep(0.3)
    for _ in range(steps):
        robot.advance()
        time.sleep(0.03)
    last = robot.stamp(robot.step)
    assert col.wait_for(lambda: any(p["stamp_ns"] == last for p in col.on("rlutf/robots/r1/pose")))
    sub.undeclare()
    return col


def test_counters_move_as_scans_are_processed(tmp_path: Path) -> None:
    with running_bench(tmp_path, metrics_port=0, metrics_addr="127.0.0.1") as bench:
        port = bench.service.metrics.port
        assert port is not None
        me = bench.service.settings.instance
        before = scrape(port)
        assert {name for name, _ in before} >= {
            n.removesuffix("_total") + "_total" for n in METRIC_NAMES if n.endswith("_total")
        }
        assert value(before, "rlutf_robots_held", instance=me) == 0

        col = _feed(bench, 12)
        poses = col.on("rlutf/robots/r1/pose")
        after = scrape(port)
        # odometry, initial pose and scans of r1 (the map put is not a robot message)
        assert value(after, "rlutf_messages_received_total", instance=me) >= 2 * 12 + 2
        published = sum(
            value(after, "rlutf_poses_published_total", instance=me, status=s)
            for s in ("tracking", "corrected", "lost")
        )
        # the pose of the last scan has arrived: nothing is in flight
        assert published == bench.service.stats.processed >= len(poses) > 0
        assert value(after, "rlutf_scan_to_pose_latency_seconds_count", instance=me) == published
        assert value(after, "rlutf_scan_to_pose_latency_seconds_sum", instance=me) > 0
        # every latency is under a second here: the +Inf and 1 s buckets hold them all
        assert value(
            after, "rlutf_scan_to_pose_latency_seconds_bucket", instance=me, le="1.0"
        ) == pytest.approx(published)
        assert value(after, "rlutf_worker_compute_seconds_count", instance=me) > 0
        assert value(after, "rlutf_robots_held", instance=me) == 1
        assert value(after, "rlutf_robots_owned", instance=me) == 1
        assert value(after, "rlutf_robots_lost", instance=me) == 0
        assert value(after, "rlutf_messages_rejected_total", instance=me) == 0

        # a payload that is not a LaserScan: received and rejected
        bench.client.put("rlutf/robots/r1/scan", b'{"stamp_ns": "soon"}', encoding=JSON)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            rejected = scrape(port)
            if value(rejected, "rlutf_messages_rejected_total", instance=me) == 1:
                break
            time.sleep(0.05)
        assert value(rejected, "rlutf_messages_rejected_total", instance=me) == 1
        assert value(rejected, "rlutf_messages_received_total", instance=me) == (
            value(after, "rlutf_messages_received_total", instance=me) + 1
        )
        # health and metrics read the same counters
        assert bench.service.stats.rejected == 1

    with pytest.raises(urllib.error.URLError):  # closed with the service
        scrape(port)


def families(port: int) -> set[str]:
    """The metric names of a scrape as PromQL sees them (counters with their ``_total``)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        text = reply.read().decode()
    return {
        f.name + "_total" if f.type == "counter" else f.name
        for f in text_string_to_metric_families(text)
    }


def bases() -> set[str]:
    return {n.removesuffix("_total") for n in METRIC_NAMES}


def test_every_exported_name_is_listed(tmp_path: Path) -> None:
    """METRIC_NAMES (what the dashboard and docs use) is exactly what a scrape shows."""
    with running_bench(tmp_path, metrics_port=0, metrics_addr="127.0.0.1") as bench:
        assert bench.service.metrics.port is not None
        exported = families(bench.service.metrics.port)
    # prometheus_client adds a {name}_created gauge to every counter and histogram (when it
    # started); nothing of ours.
    created = {
        n for n in exported if n.endswith("_created") and n.removesuffix("_created") in bases()
    }
    exported -= created
    assert len(created) == 3  # poses, latency, compute: the families made in the process
    assert exported == METRIC_NAMES
    assert all(name.startswith("rlutf_") for name in exported)


def test_off_by_default(bench: Bench) -> None:
    assert isinstance(bench.service.metrics, NullMetrics)
    assert bench.service.metrics.port is None


def test_instances_in_one_process_keep_their_own_registries() -> None:
    a = ServiceMetrics("a", free_port(), "127.0.0.1")
    b = ServiceMetrics("b", free_port(), "127.0.0.1")
    a.pose("tracking")
    a.latency(3.0)
    # the global registry would have refused the second set of names
    assert a.registry is not b.registry
    assert (
        a.registry.get_sample_value(
            "rlutf_poses_published_total", {"instance": "a", "status": "tracking"}
        )
        == 1
    )
    assert (
        b.registry.get_sample_value(
            "rlutf_poses_published_total", {"instance": "b", "status": "tracking"}
        )
        == 0
    )
    assert (
        a.registry.get_sample_value(
            "rlutf_scan_to_pose_latency_seconds_bucket", {"instance": "a", "le": "0.005"}
        )
        == 1
    )


def test_a_port_in_use_fails_the_start(tmp_path: Path) -> None:
    with running_bench(tmp_path / "a", metrics_port=0, metrics_addr="127.0.0.1") as bench:
        taken = bench.service.metrics.port
        assert taken is not None
        with pytest.raises(OSError):
            running_bench(tmp_path / "b", metrics_port=taken, metrics_addr="127.0.0.1").__enter__()
