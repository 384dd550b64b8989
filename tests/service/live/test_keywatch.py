"""Issue 19, item 8: every put or DELETE on a key no part of the service takes gets an Event.

Keys with extra levels, unknown leaves, DELETEs on robot and map keys and puts on other keys
under the prefix: an Event each class, at most one per interval (the rest counted in the next
one); a key with a newline cannot forge a line of the service's log.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pytest
from service_harness import Collector, running_bench

from service.keys import Keys, printable


@pytest.mark.parametrize(
    ("key", "delete", "kind"),
    [
        ("rlutf/robots/r1/scan/x", False, "extra_levels"),
        ("rlutf/robots/r1", False, "extra_levels"),
        ("rlutf/robots/r1/scans", False, "unknown_leaf"),
        ("rlutf/robots/r1/scan", True, "delete"),
        ("rlutf/robots/r1/pose", True, "delete"),
        ("rlutf/maps/m1", True, "map_deleted"),
        ("rlutf/maps/m1/v2", False, "extra_levels"),
        ("rlutf/foo", False, "unknown_key"),
        ("rlutf/service/x/health", False, "unknown_key"),
        ("rlutf/events", True, "unknown_key"),
    ],
)
def test_odd_keys_are_classified(key: str, delete: bool, kind: str) -> None:
    odd = Keys().odd(key, delete)
    assert odd is not None and odd.kind == kind
    assert key in odd.message


@pytest.mark.parametrize(
    "key",
    [
        "rlutf/robots/r1/scan",
        "rlutf/robots/r1/odom",
        "rlutf/robots/r1/initialpose",
        "rlutf/robots/r1/relocalize",
        "rlutf/robots/r1/pose",
        "rlutf/robots/r1/events",
        "rlutf/maps/m1",
        "rlutf/events",
        "rlutf/maphealth/m1",  # another instance's or process's MapHealth
        "other/robots/r1/scan/x",
    ],
)
def test_the_service_keys_are_not_odd(key: str) -> None:
    assert Keys().odd(key, delete=False) is None


def test_maphealth_keys_beyond_the_service_s_are_odd() -> None:
    extra = Keys().odd("rlutf/maphealth/m1/x", delete=False)
    assert extra is not None and extra.code == "invalid_key"
    deleted = Keys().odd("rlutf/maphealth/m1", delete=True)
    assert deleted is not None and deleted.code == "invalid_key"


def test_printable_escapes_control_characters() -> None:
    assert (
        printable("rlutf/robots/a\nWARNING forged/scan") == "rlutf/robots/a\\x0aWARNING forged/scan"
    )
    assert printable("a\x1b[31mred\u2028") == "a\\x1b[31mred\\u2028"
    assert printable("plain/key-é") == "plain/key-é"
    assert printable("x" * 300, limit=10) == "x" * 10 + "..."


def _events(col: Collector) -> list[dict[str, object]]:
    return col.on("rlutf/events")


@pytest.mark.integration
def test_odd_keys_get_one_event_per_class_and_interval(tmp_path: Path) -> None:
    with running_bench(tmp_path, event_interval_s=30.0) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/events", col)
        time.sleep(0.5)
        sent = ["rlutf/robots/r1/scan/x", "rlutf/robots/r1/scans", "rlutf/foo/bar"]
        for _ in range(200):  # a flood: one Event per class
            for key in sent:
                b.client.put(key, b"{}")
        b.client.delete("rlutf/robots/r1/scan")
        b.client.delete("rlutf/maps/m9")

        def codes() -> list[tuple[object, object]]:
            return sorted((e["code"], e["key"]) for e in _events(col))

        expected = sorted(
            [("invalid_key", k) for k in sent]
            + [("invalid_key", "rlutf/robots/r1/scan"), ("map_deleted", "rlutf/maps/m9")]
        )
        assert col.wait_for(lambda: codes() == expected), codes()
        time.sleep(0.5)
        assert codes() == expected, "a flood must cost one Event per class and interval"
        by_key = {e["key"]: e for e in _events(col)}
        assert "has 3 level(s)" in str(by_key["rlutf/robots/r1/scan/x"]["message"])
        assert "DELETE" in str(by_key["rlutf/robots/r1/scan"]["message"])
        health = b.service.stats.rejected
        assert health >= 3 * 200 + 2
        sub.undeclare()


@pytest.mark.integration
def test_the_held_back_count_is_in_the_next_event(tmp_path: Path) -> None:
    with running_bench(tmp_path, event_interval_s=0.5) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/events", col)
        time.sleep(0.5)
        for _ in range(20):
            b.client.put("rlutf/robots/r1/scan/x", b"{}")
        time.sleep(0.8)
        b.client.put("rlutf/robots/r1/scan/x", b"{}")
        assert col.wait_for(lambda: len(_events(col)) == 2)
        assert "(19 more like it since the last such Event)" in str(_events(col)[1]["message"])
        sub.undeclare()


@pytest.mark.integration
def test_a_newline_in_a_key_does_not_forge_a_log_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    forged = "rlutf/robots/bad\nERROR rlutf: forged/scan"
    with caplog.at_level(logging.INFO), running_bench(tmp_path) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/events", col)
        time.sleep(0.5)
        b.client.put(forged, b"{}")
        assert col.wait_for(lambda: any(e["key"] == forged for e in _events(col)))
        sub.undeclare()
    lines = [r.getMessage() for r in caplog.records if "forged" in r.getMessage()]
    assert lines, "the Event is logged"
    assert all("\n" not in line for line in lines)
    assert any("bad\\x0aERROR" in line for line in lines)
