"""The robots' inputs taken from a Zenoh FIFO channel by one loop thread (``intake = "loop"``).

With a callback subscriber, Zenoh calls into Python once per sample on its own thread, which
must take the GIL each time: in a busy process that thread waits for the GIL about as long as it
works, and samples queue up behind it. Here the subscriber puts samples into a FIFO channel
on Zenoh's side, without Python, and one thread of ours takes them in: everything that arrived
(up to :data:`BATCH`) goes through the same checks as a callback's
(:meth:`service.live.intake.Intake.on_robot_sample`), in arrival order, then, when the robots
run in this process (:class:`~service.live.shards.LoopShard`), the loop runs the ready batches
itself before it takes in more. A scan that a newer one of its robot replaced meanwhile is
dropped in its mailbox and counted, as always. The loop drains the channel whole, then runs
ready batches for :data:`RUN_BUDGET_S` at most (one at least) before it drains it again, so
that under overload it is the mailboxes, which count what they drop, that absorb the excess,
not the channel. The channel holds :data:`CAPACITY` samples, a fraction of a second of a fleet.

When nothing arrived and nothing was ready, the thread waits ``wait_s`` (the ``intake_wait_s``
setting, 10 ms by default) before it looks again: what came meanwhile is taken in and answered
in one round, back to back. Updates run so cost less CPU than updates run one at a time as
their scans come (fewer wake-ups of the thread, and the localizer's code and data still in the
caches from the update before: 0.60 against 0.76 ms of the service's CPU per scan at 200
robots, BENCHMARKS.md, "Inputs taken in rounds"), at up to ``wait_s`` more latency. Under
load the loop does not wait at all. A control message (a new map) from another thread is
applied within that long too.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from service.live.publishing import HOLD_S, PoseOut
from service.live.shards import LoopShard

log = logging.getLogger(__name__)

#: Samples the Zenoh channel holds before it holds up the link: about a third of a second of 100
#: robots' inputs. A sample waiting in the channel can keep the whole buffer it was received in
#: alive, so the channel's memory is not its samples' size (20,000 let a process grow past
#: 600 MB under overload; BENCHMARKS.md, "Fleet: processes behind one host").
CAPACITY = 1_000
#: Samples taken in at most before some ready batches run (the channel is drained whole
#: first, unless it holds more than this).
BATCH = CAPACITY
#: Seconds of ready batches run at most (one batch at least) before the channel is drained
#: again: under overload the inputs keep coming in (and a robot's older scan is dropped in its
#: mailbox, counted) instead of piling up in the channel until it holds up the link (where a
#: drop would not be counted). A budget of time rather than of batches, so that a round's updates
#: keep their share of the thread however many inputs came in (whether it answers more than 8
#: batches a round did is within the run-to-run spread so far: BENCHMARKS.md, "Fleet: processes
#: behind one host").
RUN_BUDGET_S = 0.02
#: Seconds an idle loop waits before it looks again (the ``intake_wait_s`` setting's default).
WAIT_S = 0.01


class InputLoop:
    """Take samples from a FIFO subscriber on one thread and run the ready batches.

    Args:
        on_sample: the checks of one sample (a callback subscriber's callback).
        shard: the shard whose batches this thread runs, if the robots run in this process.
        poses: where the poses of those batches go out: their puts are held and put together
            after each batch once the oldest is :data:`HOLD_S` old, and at the end of a round.
        wait_s: how long the loop waits when it has taken in and answered everything.
    """

    def __init__(
        self,
        on_sample: Callable[[zenoh.Sample], None],
        shard: LoopShard | None,
        poses: PoseOut | None = None,
        wait_s: float = WAIT_S,
    ) -> None:
        self._on_sample = on_sample
        self._shard = shard
        self._poses = poses
        self._wait_s = wait_s
        self._sub: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, session: zenoh.Session, key: str) -> None:
        """Subscribe to ``key`` and start the thread."""
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(CAPACITY))
        self._thread = threading.Thread(target=self._run, name="rlutf-inputs", daemon=True)
        self._thread.start()

    def _take(self) -> int:
        taken = 0
        while taken < BATCH:
            sample = self._sub.try_recv()
            if sample is None:
                break
            taken += 1
            try:
                self._on_sample(sample)
            except Exception:  # the checks never raise; if they do, the loop goes on
                log.exception("input %s", sample.key_expr)
        return taken

    def _run(self) -> None:
        shard = self._shard
        poses = self._poses
        after: Callable[[], object] | None = None
        if poses is not None:
            poses.hold()
            after = functools.partial(poses.release, HOLD_S)
        while not self._stop.is_set():
            taken = self._take()
            until = time.perf_counter() + RUN_BUDGET_S
            ran = shard.run_ready(until=until, after_batch=after) if shard is not None else 0
            if poses is not None:
                poses.release()
            if not taken and not ran:
                self._stop.wait(self._wait_s)
        while self._take():  # what arrived before the stop is taken in, not lost
            pass
        if poses is not None:
            poses.release()

    def close(self) -> None:
        """Stop taking inputs (those already received are taken in first), unsubscribe."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


class Inputs:
    """The robots' input subscription the settings ask for (``intake``).

    ``callback``: one callback subscriber, whose callbacks run on one Zenoh thread, in arrival
    order (a subscriber per leaf would each have a thread of its own, and a robot's scan could
    overtake the odometry put before it). ``loop``: an :class:`InputLoop`. Either way it never
    receives what this service puts (Events and poses go to other sessions only), so nothing
    here waits on a queue only its own thread drains; leaves that are no input or pose (other
    instances' Events) are dropped on the key, before any decode.
    """

    def __init__(
        self,
        on_sample: Callable[[zenoh.Sample], None],
        shard: LoopShard | None,
        intake: str = "callback",
        poses: PoseOut | None = None,
        wait_s: float = WAIT_S,
    ) -> None:
        self._on_sample = on_sample
        self.loop = InputLoop(on_sample, shard, poses, wait_s) if intake == "loop" else None
        self._sub: Any = None

    def start(self, session: zenoh.Session, key: str) -> None:
        """Subscribe to ``key``."""
        if self.loop is not None:
            self.loop.start(session, key)
        else:
            self._sub = session.declare_subscriber(key, self._on_sample)

    def close(self) -> None:
        """Unsubscribe (a loop takes in what was received first)."""
        if self.loop is not None:
            self.loop.close()
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
