"""Per-robot mailboxes and the worker shards that run the localizers.

Zenoh callbacks only validate and call :meth:`Dispatcher.submit`. Each robot has a mailbox of its
inputs in arrival order; a newer scan replaces an unprocessed older one (the drop is counted and
reported), odometry and initial poses are never dropped. A robot is given, when first seen, to
the shard with the fewest robots; a shard runs one batch per robot at a time, so one robot's
updates are sequential while different robots run in parallel. A shard is a worker process (the
default: numpy work holds the GIL, so threads would cap the service at one core) or, with
``workers=0``, threads in this process.

Inside a worker process (:mod:`service.live.worker`), the batches of robots that may take long
(relocalizing or lost: :meth:`FleetEngine.expects_long_update`) run on a pool of ``threads - 1``
threads beside the thread that reads the pipe and runs every other batch: a relocalization (0.1
to 2 s of compiled search, which releases the GIL) then holds up only its own robot, and
ordinary updates do not contend for the GIL with each other. With ``workers=0``, the shard's
``threads`` threads take any batch. A robot's batches still run one after another, and the
robots share nothing but the maps (looked up under a lock), so each robot's poses are the same
as in replay whatever the threads do.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rlutf.localizer import LocalizerConfig
from service.engine import FleetEngine, Outbound
from service.keys import InputKind, Keys, Message
from service.live.worker import (
    Entry,
    HandOver,
    apply_control,
    evidence,
    recv,
    run_batch,
    send,
    worker_main,
)
from service.maps.book import LoadedMap

log = logging.getLogger(__name__)

#: Batches a shard may have in flight at once (for different robots), so it never waits idle;
#: a shard runs them on as many threads, so a long update holds up only its own robot.
_IN_FLIGHT = 4
#: The same for a worker process: robots whose batches are in its pipe or being computed.
_PIPE_IN_FLIGHT = 16
#: Odometry readings a mailbox holds for a robot that sends no scan before they go anyway.
_ODOM_ALONE = 32


@dataclass
class _Mailbox:
    shard: _Shard
    entries: deque[Entry] = field(default_factory=deque)
    scan: Entry | None = None  # the unprocessed scan in ``entries``, if any
    busy: bool = False
    queued: bool = False

    def worth_a_batch(self) -> bool:
        """Whether the entries are worth sending to the worker now.

        Odometry alone changes nothing that is published: it waits in the mailbox for the
        robot's next scan or request (robots send odometry just before each scan, and sending
        it alone cost a second pipe round trip per scan), up to :data:`_ODOM_ALONE` readings.
        """
        return (
            self.scan is not None
            or len(self.entries) >= _ODOM_ALONE
            or any(e.kind != "odom" for e in self.entries)
        )


@dataclass(frozen=True)
class Done:
    """Result of one robot batch: what to publish and the compute time."""

    robot: str
    outputs: list[Outbound]
    compute_s: float


OnDone = Callable[[Done], None]
OnDrop = Callable[[str, int, int], None]
"""Called with the robot, the dropped scan's stamp and when it was received."""


class _Shard:
    """A queue of ready robots served by one worker (process or thread)."""

    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        self.index = index
        self.dispatcher = dispatcher
        self.ready: deque[str] = deque()
        self.control: deque[tuple[Any, ...]] = deque()
        self.cond = threading.Condition(dispatcher.lock)
        self.in_flight = 0
        self.max_in_flight = max(_IN_FLIGHT, dispatcher.threads)
        self.robots = 0  # robots assigned to this shard
        self.threads: list[threading.Thread] = []

    def start(self) -> None:
        raise NotImplementedError

    def join(self, timeout: float) -> None:
        for t in self.threads:
            t.join(timeout)

    def take(self) -> tuple[str | None, tuple[Any, ...] | list[Entry]] | None:
        """The next control message or ready robot's batch, or ``None`` (lock held by caller).

        Returns:
            ``(None, message)`` for a control message, ``(robot, entries)`` for a batch.
        """
        if self.control:
            return None, self.control.popleft()
        if self.ready and self.in_flight < self.max_in_flight:
            robot = self.ready.popleft()
            box = self.dispatcher.boxes[robot]
            box.queued = False
            entries = list(box.entries)
            box.entries.clear()
            box.scan = None
            box.busy = True
            self.in_flight += 1
            return robot, entries
        return None

    def next_work(self) -> tuple[str | None, tuple[Any, ...] | list[Entry]] | None:
        """Block until :meth:`take` has something (lock held by caller).

        Returns:
            What :meth:`take` returns, or ``None`` when the dispatcher stops and nothing is left.
        """
        d = self.dispatcher
        while True:
            work = self.take()
            if work is not None:
                return work
            if d.stopping and not self.ready and self.in_flight == 0:
                return None
            self.cond.wait(0.5)

    def wake(self) -> bool:
        """Something was queued for this shard (lock held by caller).

        Returns:
            Whether the caller must call :meth:`drain` once it has released the lock.
        """
        self.cond.notify_all()
        return False

    def drain(self) -> None:
        """Send what :meth:`wake` found (called without the lock)."""

    def finish(self, robot: str) -> None:
        """Mark a robot's batch done and requeue it if more arrived (lock held by caller)."""
        box = self.dispatcher.boxes[robot]
        box.busy = False
        self.in_flight -= 1
        if box.entries and not box.queued and box.worth_a_batch():
            box.queued = True
            self.ready.append(robot)


class _ThreadShard(_Shard):
    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        super().__init__(index, dispatcher)
        d = dispatcher
        self.engine = FleetEngine(d.keys, d.config, d.event_interval_ns, evidence(d.map_health))
        self.hand_over = HandOver(self.engine)

    def start(self) -> None:
        for i in range(self.dispatcher.threads):
            t = threading.Thread(
                target=self._run, name=f"rlutf-shard-{self.index}-{i}", daemon=True
            )
            self.threads.append(t)
            t.start()

    def _run(self) -> None:
        d = self.dispatcher
        while True:
            with d.lock:
                work = self.next_work()
                if work is not None and work[0] is None:
                    # Under the lock: no batch handed out after this map can run before it.
                    apply_control(self.engine, work[1])  # type: ignore[arg-type]
                    continue
            if work is None:
                return
            robot, item = work
            assert robot is not None
            t0 = time.perf_counter()
            outputs = run_batch(self.engine, robot, item)  # type: ignore[arg-type]
            self.hand_over(outputs)
            # Published before the robot's next batch may start on another thread: its poses
            # go out (and into the log) in order.
            d.deliver(Done(robot, outputs, time.perf_counter() - t0))
            with d.lock:
                self.finish(robot)
                self.cond.notify_all()


class _ProcessShard(_Shard):
    """A worker process fed through a pipe.

    No thread of its own sends: the thread that queues work (a Zenoh callback in
    :meth:`Dispatcher.submit`, or this shard's receiving thread when a batch comes back) moves
    what is ready into :attr:`outbox` under the dispatcher's lock and, unless another thread is
    already sending, sends it after releasing the lock. A hop to a sending thread cost a thread
    wake-up and a GIL hand-off per scan. The outbox keeps the order messages were taken in (a
    map before the batches queued after it), and everything taken at once goes in one pipe
    message. Writes never block for long: at most ``max_in_flight`` batches are in the pipe.
    """

    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        super().__init__(index, dispatcher)
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        d = dispatcher
        self.process = ctx.Process(
            target=worker_main,
            args=(child, d.keys.prefix, d.config, d.event_interval_ns, d.threads, d.map_health),
            name=f"rlutf-worker-{index}",
            daemon=True,
        )
        # A worker runs its batches one after another, so it idles while the main process turns
        # its answers round; with only _IN_FLIGHT batches in its pipe that round trip (a GIL
        # hand-off in the main process) capped a worker well under a core (measured: 150
        # robots, workers 28 % busy, 14 % of scans superseded). 16 batches of a few kB each
        # still fit the pipe's buffer.
        self.max_in_flight = max(_PIPE_IN_FLIGHT, dispatcher.threads)
        self.outbox: list[tuple[Any, ...]] = []
        self.sending = False
        self.gone = False

    def start(self) -> None:
        self.process.start()
        t = threading.Thread(target=self._recv, name=f"rlutf-shard-{self.index}-recv", daemon=True)
        self.threads.append(t)
        t.start()

    def wake(self) -> bool:
        while (work := self.take()) is not None:
            robot, item = work
            if robot is None:
                self.outbox.append(item)  # type: ignore[arg-type]
            else:
                batch = [(e.kind, e.payload, e.received_ns) for e in item]
                self.outbox.append(("batch", robot, batch))
        self.cond.notify_all()  # Dispatcher.stop may wait for the shard to empty
        if self.outbox and not self.sending:
            self.sending = True
            return True
        return False

    def drain(self) -> None:
        lock = self.dispatcher.lock
        while True:
            with lock:
                if not self.outbox:
                    self.sending = False
                    return
                out, self.outbox = self.outbox, []
            if self.gone:
                continue
            try:
                send(self.conn, out[0] if len(out) == 1 else ("many", out))
            except (OSError, ValueError):
                log.exception("worker %d is gone", self.index)
                self.gone = True

    def _recv(self) -> None:
        d = self.dispatcher
        while True:
            try:
                msg = recv(self.conn)
            except (EOFError, OSError):
                return
            if msg[0] == "stopped":
                return
            _, robot, outputs, compute_s = msg
            with d.lock:
                self.finish(robot)
                send = self.wake()
            if send:
                self.drain()  # the worker gets its next batches before we publish these
            d.deliver(Done(robot, outputs, compute_s))

    def stop(self, deadline: float) -> None:
        """Wait for what is queued and in flight, then tell the worker to stop."""
        d = self.dispatcher
        with d.lock:
            send = self.wake()
        if send:
            self.drain()
        with d.lock:
            while (self.ready or self.in_flight) and not self.gone:
                if time.monotonic() >= deadline:
                    break
                self.cond.wait(0.1)
            self.outbox.append(("stop",))
            send = not self.sending
            self.sending = True
        if send:
            self.drain()

    def join(self, timeout: float) -> None:
        super().join(timeout)
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()


class Dispatcher:
    """Mailboxes and shards.

    Args:
        keys: key layout.
        config: localizer parameters.
        workers: worker processes; 0 runs one shard on threads of this process; -1 one process
            per core.
        event_interval_ns: least time between two events of one code for one robot.
        on_done: called (from a shard's thread) with each finished batch.
        on_drop: called (under the dispatcher's lock, keep it short) when a scan is replaced.
        threads: threads per shard running different robots' batches at once.
        map_health: count the scans' map health evidence (:mod:`service.maphealth`).
    """

    def __init__(
        self,
        keys: Keys,
        config: LocalizerConfig,
        workers: int,
        event_interval_ns: int,
        on_done: OnDone,
        on_drop: OnDrop,
        threads: int = _IN_FLIGHT,
        map_health: bool = True,
    ) -> None:
        self.keys = keys
        self.map_health = map_health
        self.threads = max(1, threads)
        self.config = config
        self.event_interval_ns = event_interval_ns
        self.on_done = on_done
        self.on_drop = on_drop
        self.lock = threading.Lock()
        self.boxes: dict[str, _Mailbox] = {}
        self.stopping = False
        self.dropped = 0
        count = (os.cpu_count() or 1) if workers < 0 else workers
        self.processes = count > 0
        if count == 0:
            self.shards: list[_Shard] = [_ThreadShard(0, self)]
        else:
            self.shards = [_ProcessShard(i, self) for i in range(count)]

    def start(self) -> None:
        """Start the shards (worker processes take a moment to import numpy)."""
        if self.processes:
            # One BLAS thread per worker: the workers already fill the cores, and BLAS threads
            # contending with them cost more than they save on the small products of an update.
            os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        for s in self.shards:
            s.start()

    def submit(
        self, robot: str, kind: InputKind, payload: bytes, message: Message, received_ns: int
    ) -> None:
        """Hand one validated input to its robot's mailbox (called from Zenoh callbacks)."""
        entry = Entry(
            kind, payload, None if self.processes else message, received_ns, message.stamp_ns
        )
        send = False
        with self.lock:
            if self.stopping:
                return
            box = self.boxes.get(robot)
            if box is None:
                # A robot's localizer lives in one worker for good: balance robot counts (a hash
                # of a few dozen ids can leave one worker a fifth busier than the other).
                shard = min(self.shards, key=lambda s: s.robots)
                shard.robots += 1
                box = self.boxes[robot] = _Mailbox(shard)
            if kind == "scan":
                old = box.scan
                if old is not None:
                    box.entries.remove(old)
                    self.dropped += 1
                    self.on_drop(robot, old.stamp_ns, old.received_ns)
                box.scan = entry
            box.entries.append(entry)
            if not box.busy and not box.queued and box.worth_a_batch():
                box.queued = True
                box.shard.ready.append(robot)
                send = box.shard.wake()
        if send:
            box.shard.drain()  # on this thread: no hop to a sending thread

    def broadcast_map(self, loaded: LoadedMap) -> None:
        """Send a map version to every shard, ahead of any batch queued after this call.

        The caller holds :attr:`lock`, and took the map's receive time under it: then no input
        received later can reach a worker before the map.
        """
        geometry: Any = loaded.world if not self.processes else loaded.world.to_geojson()
        msg = ("map", loaded.map_id, loaded.version, geometry, loaded.received_ns)
        for s in self.shards:
            s.control.append(msg)
            s.cond.notify_all()

    def flush(self) -> None:
        """Send what waits in the shards' queues (after :meth:`broadcast_map`, lock released)."""
        for s in self.shards:
            with self.lock:
                send = s.wake()
            if send:
                s.drain()

    def deliver(self, done: Done) -> None:
        """Pass a finished batch on (from a shard thread)."""
        try:
            self.on_done(done)
        except Exception:
            log.exception("publishing the results of %s failed", done.robot)

    def pending(self) -> int:
        """Inputs waiting in mailboxes."""
        with self.lock:
            return sum(len(b.entries) for b in self.boxes.values())

    def stop(self, timeout: float = 10.0) -> None:
        """Take no more input, finish what is queued and in flight, stop the shards."""
        with self.lock:
            self.stopping = True
            for s in self.shards:
                s.cond.notify_all()
        deadline = time.monotonic() + timeout
        for s in self.shards:
            if isinstance(s, _ProcessShard):
                s.stop(deadline)
        for s in self.shards:
            s.join(max(deadline - time.monotonic(), 0.1))
