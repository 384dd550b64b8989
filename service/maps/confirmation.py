"""A service loads a map put once the store holds it, so that the two never disagree.

Every service process sees a map put on the bus, and so does the store: under a flood of puts
the store drops some (``map_dropped``: :mod:`service.maps.store`). A service that loaded the
puts it saw loaded those too, and its robots ran on a map version the store never held, until a
restart switched them back. So a service asks the store what it holds of the map
(:class:`~schemas.answers.StoredVersion`) after a put that is new to it, and waits for its
word (:func:`await_store`): the store holds the put (load it), holds a version the put cannot
beat (refused, or superseded by a later put), or has no put of the map left to store and does
not hold this one (it dropped it). A store that answers nothing is no store with a version rule
(zenohd's storage manager): the service applies the rule to the versions it holds itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Literal, NamedTuple

from schemas import StoredVersion
from service.maps.book import Held, put_verdict

#: Seconds a service waits at most for the store's word on a put (the store may have many big
#: puts to check before it); past them, the put is not loaded now, and the service loads what
#: the store holds once it has stored its puts of the map.
CONFIRM_S = 10.0
#: Seconds after a put's arrival before a store that neither holds it nor has a put of the map
#: waiting counts as having dropped it: the store may see a put a little later than a service.
SETTLE_S = 0.5
#: First and longest pause between two questions to the store, seconds.
FIRST_POLL_S = 0.02
LAST_POLL_S = 0.25

Word = Literal["absent", "stored", "refused", "dropped", "unconfirmed"]
"""``absent``: no store answers; ``stored``: it holds the put; ``refused``: it holds a version
the put does not beat; ``dropped``: it neither holds the put nor has a put of the map to store;
``unconfirmed``: it still had puts of the map to store when the wait ended."""


class StoreWord(NamedTuple):
    """What the store made of a put, and its last answer (``None`` when no store answers)."""

    word: Word
    answer: StoredVersion | None


def store_word(answer: StoredVersion | None, version: int, digest: str) -> Word | None:
    """What one answer of the store says of a put of ``version`` with content ``digest``;
    ``None``: the store has puts of the map to store yet, which may hold it."""
    if answer is None:
        return "absent"
    held = answer.held
    if held == (version, digest) and not answer.removed:
        return "stored"
    if held is not None and put_verdict(held, version, digest) == "conflict":
        return "refused"  # the version to beat never goes down: final
    return None if answer.pending else "dropped"


def await_store(
    ask: Callable[[], StoredVersion | None],
    version: int,
    digest: str,
    arrived: float,
    within_s: float = CONFIRM_S,
    settle_s: float = SETTLE_S,
    clock: Callable[[], float] = time.monotonic,
    pause: Callable[[float], object] = time.sleep,
) -> StoreWord:
    """Ask the store (``ask``) until it has a word on a put of ``version`` with content
    ``digest`` that arrived at ``arrived`` (``clock`` time), or ``within_s`` seconds passed.

    A ``dropped`` word counts only from ``settle_s`` after the put's arrival (before, the store
    may not have seen it yet). ``pause`` waits between two questions, which come more slowly
    while the store stays busy.
    """
    deadline = clock() + within_s
    wait = FIRST_POLL_S
    while True:
        answer = ask()
        word = store_word(answer, version, digest)
        now = clock()
        if word == "dropped" and now < arrived + settle_s:
            word = None
        if word is not None:
            return StoreWord(word, answer)
        if now >= deadline:
            return StoreWord("unconfirmed", answer)
        pause(wait)
        wait = min(wait * 2, LAST_POLL_S)


class StoreWatch:
    """What a service without a store of its own fetches after a look at the versions the
    store holds: the puts that never reached it (Zenoh drops a message that a link cannot take
    in time; a router sends one of many fragments on within 50 ms or drops it), so that it ends
    as if it had seen every put since it started. The first look only notes what the store held
    before; a map is fetched once the store holds it with no put of it left to store."""

    def __init__(self) -> None:
        #: The version the store held of each map at the last look (``None``: not looked yet).
        self.seen: dict[str, int] | None = None

    def behind(self, held: Mapping[str, Held], stored: Mapping[str, StoredVersion]) -> list[str]:
        """The maps to fetch: held here (``held``: version and digest by map id) in an older
        version than the store's, or not held and put since the last look (``stored``: the
        store's answers by map id)."""
        behind = []
        seen, self.seen = self.seen, {}
        for map_id, answer in stored.items():
            if answer.removed or answer.pending or answer.version is None:
                continue
            mine = held.get(map_id)
            new = mine is None and seen is not None and seen.get(map_id, -1) < answer.version
            if new or (mine is not None and answer.version > mine[0]):
                behind.append(map_id)
            if not new:  # one not fetched yet is looked for again
                self.seen[map_id] = answer.version
        return sorted(behind)


def unconfirmed_message(map_id: str, version: int, answer: StoredVersion) -> str:
    """Event ``map_unconfirmed``'s message: a put of ``version`` the store did not say it holds
    within :data:`CONFIRM_S` (``answer``: its last word), not loaded."""
    held = "nothing" if answer.version is None else f"version {answer.version}"
    return (
        f"map {map_id} version {version} put not loaded: the store did not say it holds it "
        f"within {CONFIRM_S:g} s (it holds {held}, {answer.pending} put(s) of the map wait to be "
        "stored there); this service loads what the store holds once they are stored"
    )


def dropped_message(
    map_id: str, dropped: int, size: int, waiting: int, waiting_mb: float, follow: bool
) -> str:
    """Event ``map_dropped``'s message: ``dropped`` puts not loaded (the last ``size`` bytes),
    ``waiting`` puts (``waiting_mb``) waiting to be checked; ``follow``: the stored version is
    loaded once they are done (else the service follows too many maps' dropped puts already)."""
    then = (
        f"when they are done the service loads what the store holds for {map_id}"
        if follow
        else f"put {map_id} again (the puts of many other maps are already dropped)"
    )
    return (
        f"{dropped} map put(s) not loaded ({size} bytes, this one): {waiting} map puts "
        f"({waiting_mb:.1f} MB) already wait to be checked; {then}"
    )
