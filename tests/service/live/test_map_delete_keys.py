"""A DELETE on a map key whose id is no map id removes nothing, and its Event says so.

Found by a reviewer: a DELETE on ``rlutf/maps/*`` (or ``rlutf/maps/**``) got two Events that
contradicted each other, ``invalid_map`` from the store (the id is no map id) and a warning
``map_deleted`` ("the map is removed from the store"), though nothing was removed.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from service_harness import Collector, running_bench

from service.keys import Keys


@pytest.mark.parametrize("key", ["rlutf/maps/*", "rlutf/maps/**", "rlutf/maps/a$*"])
def test_a_delete_on_no_map_id_is_no_removal(key: str) -> None:
    odd = Keys().odd(key, delete=True)
    assert odd is not None and odd.code == "invalid_key" and odd.level == "error"
    assert "nothing is removed" in odd.message


def test_a_delete_on_a_map_id_is_still_said_to_remove_it() -> None:
    odd = Keys().odd("rlutf/maps/m1", delete=True)
    assert odd is not None and odd.kind == "map_deleted"


@pytest.mark.integration
def test_a_wildcard_delete_gets_no_map_deleted_event_and_removes_nothing(tmp_path: Path) -> None:
    with running_bench(tmp_path) as bench:
        events = Collector()
        sub = bench.client.declare_subscriber("rlutf/events", events)
        bench.put_map()
        time.sleep(0.5)
        bench.client.delete("rlutf/maps/*")
        assert events.wait_for(
            lambda: any("nothing is removed" in e["message"] for e in events.on("rlutf/events"))
        )
        time.sleep(0.3)
        assert not [e for e in events.on("rlutf/events") if e["code"] == "map_deleted"]
        assert [str(r.ok.key_expr) for r in bench.client.get("rlutf/maps/m1") if r.ok] == [
            "rlutf/maps/m1"
        ]
        sub.undeclare()
