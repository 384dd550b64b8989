"""Sessions on one host do not share memory pools (issue 21): zenoh's shared-memory transport
makes a 16 MB pool per session that puts messages over 3 kB, mapped by every session it
reaches; the service's processes and simulated robots share a host."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import zenoh

from service.live.sessions import TX_QUEUE_BATCHES, client_config, free_port, session_config

pytestmark = pytest.mark.integration


def _shmem_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssShmem:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no RssShmem")


def _shared_after_puts(endpoint: str, zenoh_default: bool = False) -> float:
    """RssShmem growth of this process (a router and 4 clients) after scan-sized puts."""
    configs = [session_config("router", listen=[endpoint])]
    configs += [client_config(endpoint) for _ in range(4)]
    if zenoh_default:
        for config in configs:
            config.insert_json5("transport/shared_memory/enabled", "true")
    received: list[int] = []
    before = _shmem_mb()
    with zenoh.open(configs[0]) as router:
        sub = router.declare_subscriber("t/*", lambda s: received.append(len(s.payload)))
        clients = [zenoh.open(config) for config in configs[1:]]
        try:
            time.sleep(0.5)
            for _ in range(5):
                for i, c in enumerate(clients):
                    c.put(f"t/{i}", bytes(8000))
                time.sleep(0.1)
            end = time.monotonic() + 5.0
            while len(received) < 20 and time.monotonic() < end:
                time.sleep(0.05)
            grown = _shmem_mb() - before
        finally:
            for c in clients:
                c.close()
            sub.undeclare()
    assert len(received) == 20 and set(received) == {8000}
    return grown


def test_sessions_on_one_host_share_no_memory_pools() -> None:
    assert _shared_after_puts(f"tcp/127.0.0.1:{free_port()}") < 4.0


def test_with_zenohs_default_they_would() -> None:
    """The measure above can fail: zenoh's own default maps 16 MB a session."""
    assert _shared_after_puts(f"tcp/127.0.0.1:{free_port()}", zenoh_default=True) >= 16.0


def test_links_queue_a_fleets_bursts_unless_a_file_says_otherwise(tmp_path: Path) -> None:
    """A router drops a sample sent with congestion control "drop" once the link to a
    subscriber has been full for a millisecond: each link holds 16 batches of data (zenoh's
    default, 2, lost bursts of scans on a busy host: BENCHMARKS.md, "Scans lost on the host's
    own links")."""
    for config in (
        session_config("router", listen=["tcp/127.0.0.1:0"]),
        client_config("tcp/127.0.0.1:7447"),
    ):
        sizes = json.loads(config.get_json("transport/link/tx/queue/size"))
        assert sizes["data"] == sizes["data_high"] == TX_QUEUE_BATCHES == 16
    with zenoh.open(session_config("router", listen=[f"tcp/127.0.0.1:{free_port()}"])):
        pass  # zenoh takes it
    file = tmp_path / "zenoh.json5"
    file.write_text("{ transport: { shared_memory: { enabled: false } } }")
    sizes = json.loads(session_config("router", file=file).get_json("transport/link/tx/queue/size"))
    assert sizes["data"] == 2  # the file decides


def test_the_service_warns_of_a_zenoh_file_with_short_send_queues(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from service.config import Settings
    from service.live.sessions import service_config, short_queues

    short = tmp_path / "short.json5"
    short.write_text('{ mode: "router" }')  # zenoh's default queues: 2 batches
    long = tmp_path / "long.json5"
    long.write_text(
        "{ transport: { link: { tx: { queue: { size: { data: 16, data_high: 16 } } } } } }"
    )
    caplog.set_level("WARNING", logger="service.live.sessions")
    service_config(Settings(zenoh_config=long))
    service_config(Settings())  # no file: the service's own 16
    assert caplog.records == []
    config = service_config(Settings(zenoh_config=short))
    assert short_queues(config) == ["data: 2", "data_high: 2"]
    [record] = caplog.records
    assert str(short) in record.getMessage() and "data: 2, data_high: 2" in record.getMessage()
