"""Map versions that cannot disagree (WIRE.md v1.2): one rule in the store, the service and the
tools that put maps, against a real service and its file-backed store on loopback."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from service_harness import WORLD, Bench, Collector, running_bench, storeless_service
from shapely import affinity

from rlutf.map import Map as World
from schemas import Map, decode, encode
from service.cli.main import main
from service.live.sessions import free_port
from service.maps import store as store_module
from service.maps.book import MapBook, MapChecker, VersionConflict, content_digest, put_verdict

JSON = zenoh.Encoding.APPLICATION_JSON
MOVED = World.from_shapely(affinity.translate(WORLD.geometry, 0.01, 0.0))


def _payload(version: int, world: World = WORLD, map_id: str = "m1") -> bytes:
    return encode(Map(map_id=map_id, version=version, geometry=world.to_geojson()))


def _stored(bench: Bench, map_id: str = "m1") -> Map | None:
    path = bench.store / f"{map_id}.json"
    return decode(Map, path.read_bytes(), max_bytes=10**8) if path.exists() else None


def _put_cli(bench: Bench, path: Path, *flags: str) -> int:
    return main(["map", "put", str(path), "--connect", bench.endpoint, "--timeout", "3", *flags])


def test_the_rule() -> None:
    held = (2, "abc")
    assert put_verdict(None, 1, "x") == "new"
    assert put_verdict(held, 3, "x") == "new"
    assert put_verdict(held, 2, "abc") == "echo"
    assert put_verdict(held, 2, "x") == "conflict"
    assert put_verdict(held, 1, "abc") == "conflict"


def test_book_refuses_older_and_same_version_with_other_content() -> None:
    book = MapBook(10**8)
    assert book.offer("m1", _payload(2), 1) is not None
    assert book.offer("m1", _payload(2), 2) is None  # an echo
    # Whitespace and key order do not make other content.
    assert book.offer("m1", json.dumps(json.loads(_payload(2)), indent=1).encode(), 3) is None
    with pytest.raises(VersionConflict, match="version 2 put, other content than the held"):
        book.offer("m1", _payload(2, MOVED), 4)
    with pytest.raises(VersionConflict, match=r"version 1 put, an older version than the held"):
        book.offer("m1", _payload(1, MOVED), 5)
    held = book.get("m1")
    assert held is not None and held.version == 2 and held.received_ns == 1


def test_book_consults_the_store_for_a_map_it_does_not_hold() -> None:
    """A service that never loaded a map still refuses a version its store refused."""
    store_holds = (3, content_digest(decode(Map, _payload(3))))
    book = MapBook(10**8)
    with pytest.raises(VersionConflict, match="held version 3"):
        book.offer("m1", _payload(1), 1, store_holds)
    assert book.get("m1") is None
    assert book.offer("m1", _payload(3), 2, store_holds) is not None  # the store's: loaded
    with pytest.raises(VersionConflict, match="held version 3"):  # the book's own now
        book.offer("m1", _payload(2), 3)


def _events(col: Collector) -> list[dict[str, Any]]:
    return list(col.on("rlutf/events"))


def _conflicts(col: Collector) -> list[dict[str, Any]]:
    return [e for e in col.on("rlutf/events") if e["code"] == "map_version_conflict"]


def test_a_conflicting_put_changes_nothing_anywhere_and_is_an_event(bench: Bench) -> None:
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", col)
    bench.put_map(version=2)
    assert col.wait_for(lambda: (s := _stored(bench)) is not None and s.version == 2)
    assert col.wait_for(lambda: bench.service.maps.get("m1") is not None)
    before_file = (bench.store / "m1.json").read_bytes()
    bench.put_map(version=2, world=MOVED)  # same version, other content
    assert col.wait_for(lambda: len(_conflicts(col)) == 1)
    bench.put_map(version=1, world=MOVED)  # older version
    assert col.wait_for(lambda: len(_conflicts(col)) == 2)
    first, second = _conflicts(col)
    assert "version 2 put" in first["message"] and "held version 2" in first["message"]
    assert "version 1 put" in second["message"] and "held version 2" in second["message"]
    assert first["key"] == "rlutf/maps/m1"
    time.sleep(0.3)
    assert (bench.store / "m1.json").read_bytes() == before_file
    held = bench.service.maps.get("m1")
    assert held is not None and held.version == 2
    assert held.digest == content_digest(decode(Map, _payload(2)))
    bench.put_map(version=2)  # an echo: no event
    time.sleep(0.5)
    assert len(_conflicts(col)) == 2
    sub.undeclare()


def test_map_put_refuses_an_older_version_and_names_the_held_one(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bench.put_map(version=2)
    assert Collector().wait_for(lambda: (s := _stored(bench)) is not None and s.version == 2)
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1, MOVED))
    assert _put_cli(bench, path, "--version", "1") == 1
    err = capsys.readouterr().err
    assert "holds version 2" in err and "--version 3" in err and "--version next" in err
    assert _put_cli(bench, path, "--version", "2") == 1  # same version, other content
    stored = _stored(bench)
    assert stored is not None and stored.version == 2
    assert content_digest(stored) == content_digest(decode(Map, _payload(2)))


def test_map_put_takes_the_next_version_by_default(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1))
    assert _put_cli(bench, path) == 0  # nothing held: version 1
    assert "version 1" in capsys.readouterr().out
    path.write_bytes(_payload(1, MOVED))  # edited, version left at 1 in the file
    assert _put_cli(bench, path) == 0
    assert "version 2" in capsys.readouterr().out
    stored = _stored(bench)
    assert stored is not None and stored.version == 2
    assert Collector().wait_for(
        lambda: (m := bench.service.maps.get("m1")) is not None and m.version == 2
    )
    assert _put_cli(bench, path) == 0  # the same map again: nothing new
    assert "unchanged" in capsys.readouterr().out
    stored = _stored(bench)
    assert stored is not None and stored.version == 2


def test_map_import_put_without_version_puts_the_next(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's case: `map import --put` printed version 1 while the store kept 2."""
    grid = np.full((60, 80), 254, dtype=np.uint8)  # a room of 4 m x 3 m at 5 cm, one pillar
    grid[:2, :] = grid[-2:, :] = grid[:, :2] = grid[:, -2:] = 0
    grid[25:35, 30:40] = 0
    (tmp_path / "room.pgm").write_bytes(b"P5\n80 60\n255\n" + grid.tobytes())
    (tmp_path / "room.yaml").write_text(
        "image: room.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    bench.put_map(version=2, map_id="sandbox")
    assert Collector().wait_for(lambda: _stored(bench, "sandbox") is not None)
    out = tmp_path / "sandbox.json"
    argv = ["map", "import", str(tmp_path / "room.yaml"), "--id", "sandbox", "--out", str(out)]
    assert main([*argv, "--put", "--connect", bench.endpoint]) == 0
    assert "version 3" in capsys.readouterr().out
    stored = _stored(bench, "sandbox")
    assert stored is not None and stored.version == 3
    assert main([*argv, "--put", "--version", "1", "--connect", bench.endpoint]) == 1
    assert "holds version 3" in capsys.readouterr().err


def test_map_put_with_no_storage_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    conf = zenoh.Config.from_json5(
        json.dumps({"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
    )
    conf.insert_json5("scouting/multicast/enabled", "false")
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1))
    with zenoh.open(conf):
        argv = ["map", "put", str(path), "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1"]
        assert main(argv) == 1
    assert "no storage answered" in capsys.readouterr().err


def test_store_and_service_agree_after_a_restart(tmp_path: Path) -> None:
    """The store's rule holds for maps it read from its files at start."""
    with running_bench(tmp_path) as b:
        b.put_map(version=2)
        assert Collector().wait_for(lambda: (s := _stored(b)) is not None and s.version == 2)
    with running_bench(tmp_path) as b:
        col = Collector()
        sub = b.client.declare_subscriber("rlutf/events", col)
        b.put_map(version=2, world=MOVED)
        assert col.wait_for(lambda: len(_conflicts(col)) == 1)
        assert b.service.maps.get("m1") is None
        stored = _stored(b)
        assert stored is not None
        assert content_digest(stored) == content_digest(decode(Map, _payload(2)))
        sub.undeclare()


def test_map_put_that_a_busy_store_drops_fails_and_says_why(
    bench: Bench,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from service.maps.book import MapChecker

    bench.put_map(version=1)
    assert Collector().wait_for(lambda: (s := _stored(bench)) is not None and s.version == 1)
    monkeypatch.setattr(store_module, "_QUEUED", 1)
    check = MapChecker.check

    def slow(checker: MapChecker, map_id: str, payload: bytes) -> Any:
        time.sleep(1.5)
        return check(checker, map_id, payload)

    monkeypatch.setattr(MapChecker, "check", slow)
    bench.put_map(version=2)  # being checked
    bench.put_map(version=3, world=MOVED)  # waits: the store's queue is full
    time.sleep(0.2)
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1, MOVED))
    code = main(["map", "put", str(path), "-e", bench.endpoint, "--timeout", "1", "--version", "9"])
    assert code == 1
    err = capsys.readouterr().err
    # The store's Event for this put, if it went out (one a second), says why at once;
    # otherwise the put is not confirmed in time, and the message names that Event.
    told = "the store did not take rlutf/maps/m1" in err and "already wait to be stored" in err
    assert told or ("version 9 was not confirmed" in err and "map_dropped" in err), err


def test_a_put_the_store_cannot_write_is_held_in_memory_written_later_and_said(
    bench: Bench,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A store that cannot write (a full disk; here its folder replaced by a file, a real write
    error) takes the put all the same, as every service on the bus loads it: it serves it from
    memory, ``rlutf map put`` says at once that it is not on disk (exit 1), and once the store can
    write again it writes it, with an Event map_write_resumed. Before, the store did not take it
    while the running service had loaded it: the two disagreed until a restart switched the
    robots back to the old map."""
    monkeypatch.setattr(store_module, "RETRY_S", 0.3)
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", col)
    bench.put_map(version=1)
    assert col.wait_for(lambda: (s := _stored(bench)) is not None and s.version == 1)
    aside = bench.store.with_name("store-aside")
    bench.store.rename(aside)
    bench.store.write_text("not a folder")
    restored = False
    try:
        path = tmp_path / "m1.json"
        path.write_bytes(_payload(1, MOVED))
        started = time.monotonic()
        assert _put_cli(bench, path, "--version", "2") == 1
        err = capsys.readouterr().err
        assert time.monotonic() - started < 3.0  # said at once, not at the timeout
        assert "taken, but the store could not write it to disk" in err, err
        assert "no storage answered" not in err, err
        # The store and the service agree: version 2, served from memory.
        assert col.wait_for(lambda: (m := bench.service.maps.get("m1")) is not None
                            and m.version == 2)  # fmt: skip
        served = [r.ok.payload.to_bytes() for r in bench.client.get("rlutf/maps/m1") if r.ok]
        assert [decode(Map, p).version for p in served] == [2]
        # Putting it again changes nothing and still says it is not on disk.
        assert _put_cli(bench, path, "--version", "2") == 1
        assert "in memory only" in capsys.readouterr().err
        failed = [e for e in _events(col) if e["code"] == "map_write_failed"]
        assert (
            failed and failed[0]["level"] == "error" and "could not write" in failed[0]["message"]
        )
        bench.store.unlink()
        aside.rename(bench.store)
        restored = True
        assert col.wait_for(lambda: (s := _stored(bench)) is not None and s.version == 2, 10.0)
        assert col.wait_for(
            lambda: any(e["code"] == "map_write_resumed" for e in _events(col)), 10.0
        )
        assert _put_cli(bench, path, "--version", "2") == 0  # on disk now: unchanged, done
    finally:
        sub.undeclare()
        if not restored:
            bench.store.unlink()
            aside.rename(bench.store)


def test_a_put_past_the_memory_the_store_holds_unwritten_is_not_taken(
    bench: Bench,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Maps the disk refuses are held in memory within a budget: past it, not taken, and the
    service beside the store does not load it either (it did: the store had handed the put on
    when it took it, before it found it could not hold it)."""
    monkeypatch.setattr(store_module, "UNWRITTEN_BYTES", 10)
    bench.put_map(version=1)
    assert Collector().wait_for(lambda: (s := _stored(bench)) is not None and s.version == 1)
    aside = bench.store.with_name("store-aside")
    bench.store.rename(aside)
    bench.store.write_text("not a folder")
    try:
        path = tmp_path / "m1.json"
        path.write_bytes(_payload(1, MOVED))
        assert _put_cli(bench, path, "--version", "2") == 1
        err = capsys.readouterr().err
        assert "the store did not take rlutf/maps/m1" in err, err
        assert "could not write it" in err and "put it again once it can write" in err, err
        assert bench.service._storage is not None
        held = bench.service._storage.held("m1")
        assert held is not None and held[0] == 1
        time.sleep(0.3)  # anything left to load
        mine = bench.service.maps.get("m1")
        assert mine is not None and mine.version == 1
    finally:
        bench.store.unlink()
        aside.rename(bench.store)


def test_a_put_after_a_remove_must_be_newer_than_the_version_removed_everywhere(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`rlutf map remove` empties the store, but a running service keeps the version it holds.
    Before, the store forgot the version: a put of version 1 afterwards was new to the store and
    older than the service's, `map put` said "stored" (exit 0), and the store held one map while
    the robots ran on another until a restart switched them. Now the store keeps the version
    removed: version 1 is refused by both (exit 1, naming the version to beat), `--version next`
    (the default) takes the one after it, and the store and the service end on the same map."""
    bench.put_map(version=2)
    assert Collector().wait_for(
        lambda: (m := bench.service.maps.get("m1")) is not None and m.version == 2
    )
    assert main(["map", "remove", "m1", "-e", bench.endpoint, "--force"]) == 0
    capsys.readouterr()
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1, MOVED))
    assert _put_cli(bench, path, "--version", "1") == 1
    err = capsys.readouterr().err
    assert "not newer than version 2 that was removed" in err or "held version 2" in err, err
    assert _stored(bench) is None  # nothing changed anywhere
    held = bench.service.maps.get("m1")
    assert held is not None and held.version == 2
    assert _put_cli(bench, path) == 0  # next: after the version removed
    assert "version 3" in capsys.readouterr().out
    assert Collector().wait_for(
        lambda: (m := bench.service.maps.get("m1")) is not None and m.version == 3
    )
    stored = _stored(bench)
    assert stored is not None and stored.version == 3
    assert not list(bench.store.glob(".m1.removed"))  # a newer version: the mark is gone


def test_map_put_says_when_a_running_service_refuses_what_the_store_took(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The store and a running service can still disagree where the store lost what it held (its
    folder replaced under a running fleet; here its file and its memory of version 3 dropped): a
    put of version 1 is new to the store and old to the service, and `map put` says so, exit 1,
    with the version both take."""
    bench.put_map(version=3)
    assert Collector().wait_for(
        lambda: (m := bench.service.maps.get("m1")) is not None and m.version == 3
    )
    storage = bench.service._storage
    assert storage is not None
    with storage._lock:  # the store's folder replaced: it holds nothing
        storage._versions.clear()
        (bench.store / "m1.json").unlink()
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(1, MOVED))
    assert _put_cli(bench, path, "--version", "1") == 1
    err = capsys.readouterr().err
    assert "a running service refused it" in err and "--version 4" in err, err


def test_a_process_without_the_store_refuses_what_the_store_refuses(bench: Bench) -> None:
    """The processes of `rlutf serve --processes N` but the host's, and any service started
    without a store, load the map puts they see. One that started after the store took version
    5 of m1 and after `rlutf map remove` of m2 at version 2 held neither, so it loaded version 3
    of m1 and version 1 of m2, which the store refused: the robots on it ran on other maps than
    the store's (a restart of the store's process switched them back). Now it asks the store
    what it holds (``{prefix}/mapversions/{map_id}``) for a map it does not hold, and refuses
    the same puts; what the store takes, it loads."""
    bench.put_map("m1", version=5)
    bench.put_map("m2", version=2)
    assert Collector().wait_for(lambda: _stored(bench, "m1") is not None)
    assert Collector().wait_for(lambda: bench.service.maps.get("m2") is not None)
    assert main(["map", "remove", "m2", "-e", bench.endpoint, "--force"]) == 0
    other = storeless_service(bench, event_interval_s=0.0)
    try:
        col = Collector()
        sub = bench.client.declare_subscriber("rlutf/events", col)
        bench.put_map("m1", version=3)  # older than the one stored
        bench.put_map("m2", version=1)  # older than the one removed
        # each refused twice: by the store's process and by the other one
        assert col.wait_for(lambda: len(_conflicts(col)) >= 4), _events(col)
        time.sleep(0.3)
        assert other.maps.get("m1") is None and other.maps.get("m2") is None
        bench.put_map("m2", version=2)  # the removed version as it was: taken everywhere
        assert col.wait_for(lambda: (m := other.maps.get("m2")) is not None and m.version == 2)
        assert _stored(bench, "m2") is not None
        sub.undeclare()
    finally:
        other.close()


def test_map_put_of_the_map_the_services_hold_ends_at_once(
    bench: Bench, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A map removed from the store and put back as it was is new to the store and the very map
    the running service holds: the service changed nothing and said nothing, so `map put` waited
    its whole --timeout for its word. Now the service says so (Event map_unchanged, info) and
    `map put` ends at once: stored, already held, exit 0."""
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", col)
    bench.put_map(version=2)
    assert col.wait_for(lambda: bench.service.maps.get("m1") is not None)
    assert main(["map", "remove", "m1", "-e", bench.endpoint, "--force"]) == 0
    capsys.readouterr()
    path = tmp_path / "m1.json"
    path.write_bytes(_payload(2))
    started = time.monotonic()
    code = main(["map", "put", str(path), "-e", bench.endpoint, "--version", "2", "--timeout", "8"])
    took = time.monotonic() - started
    out = capsys.readouterr().out
    assert code == 0 and took < 4.0, (took, out)
    assert "stored" in out and "already held" in out and "nothing changed" in out, out
    assert _stored(bench) is not None
    unchanged = [e for e in _events(col) if e["code"] == "map_unchanged"]
    assert [(e["level"], e["key"]) for e in unchanged] == [("info", "rlutf/maps/m1")]
    assert "version 2" in unchanged[0]["message"]
    sub.undeclare()


def test_map_put_gets_its_word_when_the_services_hold_back_their_events(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A service says map_unchanged (and map_version_conflict) at most once per map every
    event_interval_s. `map put` right after another put of the map gets the Event for its put
    when the interval ends, in one that counts the others held back: not at its --timeout, which
    it waited without the service's word."""
    with running_bench(tmp_path, event_interval_s=3.0) as bench:
        col = Collector()
        sub = bench.client.declare_subscriber("rlutf/events", col)
        bench.put_map(version=2)
        assert col.wait_for(lambda: bench.service.maps.get("m1") is not None)
        remove = ["map", "remove", "m1", "-e", bench.endpoint, "--force"]
        assert main(remove) == 0
        bench.put_map(version=2)  # put back by someone else: the service's word goes out
        unchanged = lambda: [e for e in _events(col) if e["code"] == "map_unchanged"]  # noqa: E731
        assert col.wait_for(lambda: len(unchanged()) == 1)
        # the service's word on an echo does not wait for the store, which may not hold it yet
        assert col.wait_for(lambda: _stored(bench) is not None)
        said = time.monotonic()
        assert main(remove) == 0
        capsys.readouterr()
        path = tmp_path / "m1.json"
        path.write_bytes(_payload(2))
        argv = ["map", "put", str(path), "-e", bench.endpoint, "--version", "2", "--timeout", "8"]
        code = main(argv)
        ended = time.monotonic()
        out = capsys.readouterr().out
        assert code == 0 and "already held" in out, out
        assert ended - said < 3.0 + 1.5, ended - said  # at the end of the interval
        assert len(unchanged()) == 2
        sub.undeclare()


def test_a_second_refused_put_after_a_remove_is_refused_too_not_unanswered(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The store's own refusal of a put not newer than a removed version went out at most once a
    second for every map at once (the service's default ``event_interval_s``): an operator's
    second `rlutf map put --version 1` right after the first waited its whole timeout and said no
    storage answered. Now the store's refusals are held back per map and the one held back goes
    out at the end of the interval: the second put gets its refusal too."""
    with running_bench(tmp_path, event_interval_s=1.0) as bench:
        bench.put_map(version=2)
        assert Collector().wait_for(
            lambda: (m := bench.service.maps.get("m1")) is not None and m.version == 2
        )
        assert main(["map", "remove", "m1", "-e", bench.endpoint, "--force"]) == 0
        path = tmp_path / "m1.json"
        path.write_bytes(_payload(1, MOVED))
        for _ in range(2):
            capsys.readouterr()
            assert _put_cli(bench, path, "--version", "1") == 1
            err = capsys.readouterr().err
            assert "not newer than version 2 that was removed" in err, err
        assert _stored(bench) is None
