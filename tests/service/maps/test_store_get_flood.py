"""A flood of gets on the stored maps costs a bounded number of file reads.

Found by a reviewer: 2,000 gets on ``rlutf/**`` against a running ``rlutf serve`` whose store
held a 20 MB map cost the service 14 s of CPU (each get read the file and made a payload of it,
in the Zenoh callback), and three robots beside it lost 70 poses. A payload read is now answered
again for a moment (:mod:`service.maps.readcache`). Real Zenoh sessions, the real file store.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from service_harness import running_bench

from service.maps.files import FileMapStore

pytestmark = pytest.mark.integration


def test_gets_of_a_map_read_its_file_a_few_times_a_second_and_see_a_new_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    reads = [0]
    real = FileMapStore.get

    def counted(store: FileMapStore, map_id: str) -> bytes | None:
        reads[0] += 1
        return real(store, map_id)

    monkeypatch.setattr(FileMapStore, "get", counted)
    with running_bench(tmp_path) as bench:
        bench.put_map("m1", version=1)
        time.sleep(0.5)
        before = reads[0]
        start, gets = time.monotonic(), 0
        while time.monotonic() - start < 2.0:
            replies = [r for r in bench.client.get("rlutf/**", timeout=2.0) if r.ok]
            maps = [r for r in replies if str(r.ok.key_expr) == "rlutf/maps/m1"]
            assert len(maps) == 1 and json.loads(maps[0].ok.payload.to_bytes())["version"] == 1
            gets += 1
        elapsed = time.monotonic() - start
        assert gets >= 50
        assert reads[0] - before <= elapsed + 2, (reads[0] - before, gets)
        storage = bench.service._storage
        assert storage is not None and storage.reads.held_bytes() > 0
        # the gets over, the payload read is let go within its second, not kept for the next
        deadline = time.monotonic() + 3.0
        while storage.reads.held_bytes() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert storage.reads.held_bytes() == 0
        bench.put_map("m1", version=2)  # a put: the next gets see it at once
        deadline = time.monotonic() + 5.0
        seen = None
        while time.monotonic() < deadline:
            got = [r.ok for r in bench.client.get("rlutf/maps/m1", timeout=2.0) if r.ok]
            seen = json.loads(got[0].payload.to_bytes())["version"] if got else None
            if seen == 2:
                break
            time.sleep(0.05)
        assert seen == 2
