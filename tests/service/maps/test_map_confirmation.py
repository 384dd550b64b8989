"""A service loads a map put once the store holds it: the store's word on a put, from its answers
on ``{prefix}/mapversions/{map_id}`` (service.maps.confirmation), and those answers."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from service_harness import JSON, WORLD, wait_until

from schemas import Map, StoredVersion, encode
from service.keys import Keys
from service.live.sessions import session_config
from service.maps.book import MapChecker
from service.maps.confirmation import await_store, store_word
from service.maps.files import FileMapStore
from service.maps.store import MapStorage, stored_version


def _payload(version: int) -> bytes:
    return encode(Map(map_id="m1", version=version, geometry=WORLD.to_geojson()))


def _answer(version: int | None, digest: str | None = "d", **kw: object) -> StoredVersion:
    return StoredVersion(map_id="m1", version=version, digest=digest, **kw)  # type: ignore[arg-type]


class _Clock:
    """A clock that the waits move on."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def pause(self, seconds: float) -> None:
        self.now += seconds


def _asking(answers: list[StoredVersion | None]) -> Iterator[StoredVersion | None]:
    yield from answers
    while True:
        yield answers[-1]


def test_one_answer_says_what_the_store_made_of_a_put() -> None:
    assert store_word(None, 3, "d") == "absent"  # no store with a version rule
    assert store_word(_answer(3), 3, "d") == "stored"
    assert store_word(_answer(3, removed=True, pending=1), 3, "d") is None  # put back: not yet
    assert store_word(_answer(4), 3, "d") == "refused"
    assert store_word(_answer(3, "other"), 3, "d") == "refused"
    assert store_word(_answer(2, pending=1), 3, "d") is None  # it may store it yet
    assert store_word(_answer(2), 3, "d") == "dropped"
    assert store_word(_answer(None, None), 3, "d") == "dropped"  # a new map's put, dropped


def test_the_wait_ends_with_the_store_word() -> None:
    clock = _Clock()
    answers = _asking([_answer(2, pending=2), _answer(2, pending=1), _answer(3)])
    word = await_store(lambda: next(answers), 3, "d", clock(), clock=clock, pause=clock.pause)
    assert word.word == "stored" and word.answer == _answer(3)
    assert clock.now - 100.0 < 0.1


def test_a_drop_counts_only_once_the_store_saw_the_put() -> None:
    """A store that holds neither the put nor a put of the map to store may not have seen the
    put yet: it counts as dropped from ``settle_s`` after the put's arrival only."""
    clock = _Clock()
    answers = _asking([_answer(2)])
    word = await_store(
        lambda: next(answers), 3, "d", clock(), settle_s=0.5, clock=clock, pause=clock.pause
    )
    assert word.word == "dropped" and 0.5 <= clock.now - 100.0 < 0.8
    clock.now += 10.0  # a put that waited here: the store saw it long ago
    word = await_store(lambda: next(answers), 3, "d", 100.0, clock=clock, pause=clock.pause)
    assert word.word == "dropped"


def test_a_store_busy_with_the_map_past_the_bound_leaves_the_put_unconfirmed() -> None:
    clock = _Clock()
    asked = 0

    def busy() -> StoredVersion:
        nonlocal asked
        asked += 1
        return _answer(2, pending=3)

    word = await_store(busy, 3, "d", clock(), within_s=5.0, clock=clock, pause=clock.pause)
    assert word.word == "unconfirmed" and word.answer == _answer(2, pending=3)
    assert 5.0 <= clock.now - 100.0 < 5.3
    assert asked < 30  # the questions come more slowly while it stays busy


def test_the_store_answers_for_a_map_asked_by_its_id_even_one_it_holds_nothing_of(
    tmp_path: Path,
) -> None:
    """A service tells a store that dropped the first put of a new map from no store at all (a
    storage manager with no version rule, which answers nothing): before, the store answered
    for the maps it held or removed only."""
    with zenoh.open(session_config("peer")) as session:
        storage = MapStorage(
            session, Keys(), FileMapStore(tmp_path), 10_000_000, checker=MapChecker(10_000_000)
        )
        try:
            answer = stored_version(session, Keys(), "m9", 2.0)
            assert answer is not None and answer.held is None and answer.pending == 0
            assert storage.answer("m9") == answer
            everything = list(session.get(Keys().map_versions, timeout=2.0))
            assert [r for r in everything if r.ok is not None] == []  # no map held, none named
        finally:
            storage.close()


def test_the_store_answers_while_it_writes_a_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The services ask the store for versions while it stores their puts: its answer waited for
    the file write in progress, in a Zenoh callback, which held up the router's other links (a
    real `rlutf serve --processes 2` lost most of a flood of puts in transit so)."""
    writing, written = threading.Event(), threading.Event()
    put = FileMapStore.put

    def slow_disk(self: FileMapStore, map_id: str, payload: bytes) -> None:
        writing.set()
        written.wait(10.0)
        put(self, map_id, payload)

    monkeypatch.setattr(FileMapStore, "put", slow_disk)
    with zenoh.open(session_config("peer")) as session:
        storage = MapStorage(
            session, Keys(), FileMapStore(tmp_path), 10_000_000, checker=MapChecker(10_000_000)
        )
        try:
            session.put("rlutf/maps/m1", _payload(1), encoding=JSON)
            assert writing.wait(10.0)
            started = time.monotonic()
            answer = stored_version(session, Keys(), "m1", 5.0)
            took = time.monotonic() - started
            assert answer is not None and answer.held is None and answer.pending == 1
            assert took < 1.0, took
            written.set()
            assert wait_until(lambda: storage.answer("m1").held is not None)
            assert storage.answer("m1").pending == 0
        finally:
            written.set()
            storage.close()
