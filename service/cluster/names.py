"""Instance names: one live instance per name, also when two start at the same instant.

An instance is known by its name (``--instance``): its liveliness token
``{prefix}/service/{instance}`` (WIRE.md) makes it a member of the fleet, and its robots, Health,
logs and pose state go under that name. Two live instances of one name each own the same robots
(each takes the other's token for its own) and answer every one of their scans twice. That token
cannot tell them apart: Zenoh shows one token per key however many sessions declare it, and takes
it away with the last one. So each instance also holds a *claim* on its name, a liveliness token
on a key of its own beside it:

    {prefix}/service/{instance}/claim/{claimed_ns}/{session}

``claimed_ns`` is when it claimed the name (ns since the Unix epoch, its own clock) and
``session`` its Zenoh session id, which no other process has. The rule:

1. Before it declares anything, an instance waits up to :data:`NAME_WAIT_S` for every token of
   its name to go, the member token and the claims of other sessions (a previous run may still be
   leaving: a process killed keeps its tokens for Zenoh's lease, 10 s); one still there refuses
   the start.
2. Then it declares its claim, follows the claims of its name for as long as it runs and, after
   :data:`SETTLE_S` (for a claim made at the same instant to reach it; twice as long as its last
   look at the bus took, if that is longer: a loaded host), asks for them once more.
3. Of two claims of one name the older one wins: the smaller ``(claimed_ns, session)``. Both
   instances rank the same two keys, so both reach the same decision, and exactly one of them
   stops. A winner learns of a loser and goes on. A loser that learns of it while it starts
   refuses to start, before it took any robot or published anything; one that learns of it later
   (two sides of a network partition, each with an instance of the name, joined again) stops at
   once, which its owner reports (an Event, exit 1).

Two instances that start together see each other's claims within :data:`SETTLE_S` unless their
clocks differ by more than that, and the older claim is the one the other sees: so the loser
learns of it while it starts. With clocks further apart the decision is the same, only maybe
later.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import zenoh

from service.keys import Keys

log = logging.getLogger(__name__)

#: Seconds a starting instance waits for a live token of its own name to go before it refuses
#: to start: a restarted instance's previous run may still be leaving (a host's process stops
#: within a second of its host's death; a session nobody closed goes at Zenoh's lease, 10 s).
NAME_WAIT_S = 12.0
#: Seconds a starting instance gives a claim declared at the same instant as its own to reach it
#: before it asks for the claims again.
SETTLE_S = 0.25
#: Younger claims on this name remembered (each said once in the log) while their tokens are
#: live; more are counted, not remembered or logged: any client may declare claim tokens, and a
#: flood of them (20,000 seen) kept one set entry and one WARNING line each, for ever.
TOLD_MAX = 64
#: What an operator does about it.
FIX = (
    "each instance needs a name of its own (--instance NAME, or `instance` in its settings; "
    "a host's processes are named INSTANCE-p0, INSTANCE-p1, ...)"
)


class NameTaken(RuntimeError):
    """Another live instance has this instance's name."""


class NameWaitStopped(RuntimeError):
    """The service was told to stop while it waited for its name's tokens to go."""


class Claim(NamedTuple):
    """One instance's claim on a name; the smaller of two claims wins (the older one)."""

    claimed_ns: int
    session: str

    def describe(self) -> str:
        """``Zenoh session 1f2e..., name claimed 2026-12-07 15:31:58 UTC``."""
        stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(self.claimed_ns / 1e9))
        return f"Zenoh session {self.session}, name claimed {stamp} UTC"


def claims_key(keys: Keys, instance: str) -> str:
    """Key expression of every claim on ``instance``'s name."""
    return f"{keys.service(instance)}/claim/*/*"


def claim_key(keys: Keys, instance: str, claim: Claim) -> str:
    """The key of ``claim``'s liveliness token."""
    return f"{keys.service(instance)}/claim/{claim.claimed_ns}/{claim.session}"


def parse_claim(keys: Keys, instance: str, key: str) -> Claim | None:
    """The claim a token's key states; ``None`` for a key that is no claim on ``instance``."""
    head = f"{keys.service(instance)}/claim/"
    if not key.startswith(head):
        return None
    stamp, _, session = key[len(head) :].partition("/")
    if not stamp.isdigit() or not session or "/" in session:
        return None
    return Claim(int(stamp), session)


def _ahead(own: Claim, older: Claim) -> str:
    """How much older ``older`` is: ``0.4 ms``, ``2.0 s``."""
    seconds = (own.claimed_ns - older.claimed_ns) / 1e9
    return f"{seconds * 1e3:.1f} ms" if seconds < 1.0 else f"{seconds:.1f} s"


class NameClaim:
    """This instance's hold on its name (see the module docstring).

    Args:
        instance: the name.
        keys: the key layout.
        on_lost: told, once, why this instance must stop, when a claim older than its own is
            seen after :meth:`take` returned (from a Zenoh thread: keep it short).
    """

    def __init__(self, instance: str, keys: Keys, on_lost: Callable[[str], None]) -> None:
        self.instance = instance
        self.keys = keys
        self.on_lost = on_lost
        self.own: Claim | None = None
        self.lost: str | None = None
        """Why this instance lost its name after it started (also said to ``on_lost``)."""
        self._beaten_by: Claim | None = None
        self._held = False
        self._told: set[Claim] = set()
        self.unlisted = 0
        """Younger claims seen past :data:`TOLD_MAX` (neither remembered nor logged)."""
        self._lock = threading.Lock()
        self._token: Any = None
        self._sub: Any = None

    def take(
        self,
        session: zenoh.Session,
        timeout: float,
        wait: float | None = None,
        settle: float = SETTLE_S,
        stop: threading.Event | None = None,
    ) -> None:
        """Claim the name, before anything else is declared.

        Args:
            session: the instance's session.
            timeout: of each liveliness get.
            wait: seconds to wait for the name's tokens to go (default :data:`NAME_WAIT_S`).
            settle: seconds a claim made at the same instant is given to arrive.
            stop: set when the service is told to stop: the wait for the name ends at once.
                (Before, SIGTERM in that wait was heard only when it ended, up to 12 s later,
                and the service then said the name was taken and exited 1.)

        Raises:
            NameTaken: another instance's token of this name is still live after ``wait``
                seconds, or another instance claimed the name at the same time, first.
            NameWaitStopped: ``stop`` was set while the name's tokens were waited for.
        """
        mine = str(session.info.zid())
        wait = NAME_WAIT_S if wait is None else wait
        deadline = time.monotonic() + wait
        asked = time.monotonic()
        stopping = stop if stop is not None else threading.Event()
        said = False
        while self._other_tokens(session, timeout, mine):
            if not said:  # the wait was silent: say it, as the wait for zenoh does
                said = True
                log.warning(
                    "an instance named %s is live on %s: waiting up to %.0f s for it to go",
                    self.instance,
                    self.keys.service(self.instance),
                    wait,
                )
            if stopping.is_set():
                raise NameWaitStopped(f"stopped while waiting for the name {self.instance}")
            if time.monotonic() >= deadline:
                raise NameTaken(
                    f"an instance named {self.instance} is live on "
                    f"{self.keys.service(self.instance)} (still after {wait:.0f} s): {FIX}"
                )
            stopping.wait(0.2)
            asked = time.monotonic()
        # A claim made at the same instant reaches this session as slowly as the bus answers
        # now: on a loaded host a look takes longer than the settle, so give it twice the look.
        settle = max(settle, 2.0 * (time.monotonic() - asked))
        self.own = Claim(time.time_ns(), mine)
        liveliness = session.liveliness()
        self._token = liveliness.declare_token(claim_key(self.keys, self.instance, self.own))
        self._sub = liveliness.declare_subscriber(
            claims_key(self.keys, self.instance), self._on_sample, history=True
        )
        time.sleep(settle)
        live = [c for c in self._claims(session, timeout) if c.session != mine]
        for claim in live:
            self._seen(claim)
        with self._lock:
            # Only a claim still live counts: one the subscriber was told of and that went
            # meanwhile (a previous run's, leaving as this one starts) is out of _told again.
            # One it was told of and the get missed (a get that timed out on a loaded host)
            # counts: it was forgotten, and both instances ran as one name for good.
            older = [c for c in {*live, *self._told} if c < self.own]
            rival = self._beaten_by = min(older) if older else None
            self._held = rival is None
        if rival is not None:
            self.close()
            raise NameTaken(self._started_together(rival))

    def confirm(self) -> None:
        """Raise :class:`NameTaken` if a claim older than this one's has been seen since
        :meth:`take` (call it right before the member token is declared)."""
        with self._lock:
            rival = self._beaten_by
        if rival is not None:
            raise NameTaken(self._started_together(rival))

    def _started_together(self, rival: Claim) -> str:
        assert self.own is not None
        return (
            f"another instance named {self.instance} started at the same time and claimed the "
            f"name {_ahead(self.own, rival)} earlier ({rival.describe()}): it keeps the name, "
            f"this one does not start; {FIX}"
        )

    def _other_tokens(self, session: zenoh.Session, timeout: float, mine: str) -> bool:
        """Whether this name's member token, or another session's claim on it, is live."""
        member = self.keys.service(self.instance)
        for reply in session.liveliness().get(f"{member}/**", timeout=timeout):  # and member
            if reply.ok is None:
                continue
            key = str(reply.ok.key_expr)
            claim = parse_claim(self.keys, self.instance, key)
            if key == member or (claim is not None and claim.session != mine):
                return True
        return False

    def _claims(self, session: zenoh.Session, timeout: float) -> list[Claim]:
        replies = session.liveliness().get(claims_key(self.keys, self.instance), timeout=timeout)
        found = (parse_claim(self.keys, self.instance, str(r.ok.key_expr)) for r in replies if r.ok)
        return [c for c in found if c is not None]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        claim = parse_claim(self.keys, self.instance, str(sample.key_expr))
        if claim is None:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._seen(claim)
        else:  # its token went: nothing of it is kept (said again if it comes back)
            with self._lock:
                self._told.discard(claim)

    def _seen(self, claim: Claim) -> None:
        """Another claim on this name is live: rank it against this one's, say so once."""
        own = self.own
        if own is None or claim.session == own.session:
            return
        with self._lock:
            if claim in self._told:
                return
            older = claim < own
            if not older and len(self._told) >= TOLD_MAX:
                self.unlisted += 1
                return
            self._told.add(claim)
            if older and (self._beaten_by is None or claim < self._beaten_by):
                self._beaten_by = claim
            news = older and self._held and self.lost is None
            if news:
                self.lost = (
                    f"another instance named {self.instance} is running ({claim.describe()}, "
                    f"{_ahead(own, claim)} before this one): it keeps the name, this instance "
                    f"stops; {FIX}"
                )
            lost = self.lost
        if not older:
            log.warning(
                "another instance named %s claimed the name after this one (%s): it stops, "
                "this one keeps the name and its robots",
                self.instance,
                claim.describe(),
            )
        elif news and lost is not None:
            log.error("%s", lost)
            self.on_lost(lost)

    def figures(self) -> dict[str, Any]:
        """This instance's claim, for its Health (``extra.claim``)."""
        if self.own is None:
            return {}
        figures: dict[str, Any] = {
            "claim": {"session": self.own.session, "claimed_ns": self.own.claimed_ns}
        }
        if self.unlisted:
            figures["younger_claims_unlisted"] = self.unlisted
        return figures

    def close(self) -> None:
        """Stop following the claims and give the name up (after the member token)."""
        for declared in (self._sub, self._token):
            if declared is not None:
                try:
                    declared.undeclare()
                except zenoh.ZError:  # already gone with the session
                    log.debug("undeclare failed", exc_info=True)
        self._sub = self._token = None


class HostNameClaim(NameClaim):
    """The claims of a host's process 0 (``rlutf serve --processes N``): its own name,
    INSTANCE-p0, and the host's, INSTANCE, which no process declares as a member but under which
    the host answers Health. Without the second, a single-process ``rlutf serve --instance
    INSTANCE`` beside the host started, took robots and answered Health as INSTANCE too.

    Args:
        instance: process 0's name.
        host: the host's name.
        keys: the key layout.
        on_lost: as :class:`NameClaim`'s, for either name.
    """

    def __init__(self, instance: str, host: str, keys: Keys, on_lost: Callable[[str], None]):
        super().__init__(instance, keys, on_lost)
        self.host = NameClaim(host, keys, self._host_lost)

    def _host_lost(self, message: str) -> None:
        with self._lock:
            first = self.lost is None
            if first:
                self.lost = message
        if first:
            self.on_lost(message)

    def take(
        self,
        session: zenoh.Session,
        timeout: float,
        wait: float | None = None,
        settle: float = SETTLE_S,
        stop: threading.Event | None = None,
    ) -> None:
        """Claim the host's name, then process 0's (:meth:`NameClaim.take`)."""
        self.host.take(session, timeout, wait, settle, stop)
        try:
            super().take(session, timeout, wait, settle, stop)
        except (NameTaken, NameWaitStopped):
            self.host.close()
            raise

    def confirm(self) -> None:
        """As :meth:`NameClaim.confirm`, for both names."""
        self.host.confirm()
        super().confirm()

    def close(self) -> None:
        """Give both names up."""
        super().close()
        self.host.close()
