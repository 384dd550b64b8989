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
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from rlutf.localizer import LocalizerConfig
from service.cores import usable_cores
from service.guard import Limits
from service.keys import InputKind, Keys, Message
from service.live.publishing import PoseOut
from service.live.robots import PLACING
from service.live.shards import (
    IN_FLIGHT,
    Done,
    LoopShard,
    Mailbox,
    OnDone,
    OnDrop,
    OnLost,
    OnSeed,
    ProcessShard,
    Shard,
    ThreadShard,
)
from service.live.stopping import ended_with_the_service
from service.live.worker import Entry, send
from service.maps.book import LoadedMap

log = logging.getLogger(__name__)

#: Versions of one map a replacement worker is sent (the engine keeps as many).
_MAP_VERSIONS_SENT = 3


class Dispatcher:
    """Mailboxes and shards.

    Args:
        keys: key layout.
        config: localizer parameters.
        workers: worker processes; 0 runs one shard on threads of this process; -1 one process
            per core this process may use (:func:`service.cores.usable_cores`: its CPU
            affinity and its container's CPU quota, not the machine's cores).
        event_interval_ns: least time between two events of one code for one robot.
        on_done: called (from a shard's thread) with each finished batch.
        on_drop: called (under the dispatcher's lock, keep it short) when a scan is replaced
            or lost with a dead worker.
        threads: threads per shard running different robots' batches at once.
        clock: the receive clock (re-seeds get fresh receive times).
        on_seed: records an input made to re-seed a robot whose worker died (lock held).
        on_lost: reports a dead worker (called without the lock).
        limits: what inputs may hold beyond the schema (:mod:`service.guard`).
        map_health: count the scans' map health evidence (:mod:`service.maphealth`).
        loop: with ``workers=0``, the batches run on the thread that takes the inputs in
            (:class:`~service.live.shards.LoopShard`, :mod:`service.live.loop`), not on
            threads of their own.
        nice: niceness the worker processes add to this one's (``os.nice``).
        stop: set when the service is told to stop (its signal handler): a worker that the
            same signal ended is not replaced (:mod:`service.live.stopping`).
    """

    def __init__(
        self,
        keys: Keys,
        config: LocalizerConfig,
        workers: int,
        event_interval_ns: int,
        on_done: OnDone,
        on_drop: OnDrop,
        threads: int = IN_FLIGHT,
        clock: Callable[[], int] = time.time_ns,
        on_seed: OnSeed | None = None,
        on_lost: OnLost | None = None,
        limits: Limits | None = None,
        map_health: bool = True,
        loop: bool = False,
        nice: int = 0,
        poses: PoseOut | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        self.keys = keys
        self.stop_requested = stop if stop is not None else threading.Event()
        self.nice = nice
        self.poses = poses
        self.limits = limits or Limits()
        self.map_health = map_health
        self.clock = clock
        self.on_seed: OnSeed = on_seed or (lambda robot, entry: None)
        self.on_lost: OnLost = on_lost or (lambda index, code, robots: None)
        self.workers_replaced = 0
        self.reseeded = 0
        # The map versions sent to the shards, oldest first: a new worker gets them all.
        self._maps: dict[str, deque[tuple[Any, ...]]] = {}
        self.threads = max(1, threads)
        self.config = config
        self.event_interval_ns = event_interval_ns
        self.on_done = on_done
        self.on_drop = on_drop
        self.lock = threading.Lock()
        self.boxes: dict[str, Mailbox] = {}
        self.stopping = False
        self.dropped = 0
        count = usable_cores() if workers < 0 else workers
        self.processes = count > 0
        self.loop: LoopShard | None = None
        if count == 0 and loop:
            self.loop = LoopShard(0, self)
            self.shards: list[Shard] = [self.loop]
        elif count == 0:
            self.shards = [ThreadShard(0, self)]
        else:
            self.shards = [ProcessShard(i, self) for i in range(count)]

    def start(self, progress: Callable[[str], None] | None = None) -> None:
        """Start the shards and wait until every worker process can localize.

        The first worker compiles the localizer's kernels if numba's cache does not hold them
        yet (about 30 s on 2 cores) and the others load them from the cache once it is done:
        several processes compiling at once on a small machine each take longer than one.

        Args:
            progress: told, once, what the wait is for when it takes more than a few seconds.

        Raises:
            RuntimeError: a worker process exited before it was ready.
        """
        if self.processes:
            # One BLAS thread per worker: the workers already fill the cores, and BLAS threads
            # contending with them cost more than they save on the small products of an update.
            os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        started = time.monotonic()
        progress = _once(progress)  # said once, whichever worker is waited for

        first, *rest = self.shards
        first.start()
        if isinstance(first, ProcessShard):
            first.wait_ready(progress, started)
            if first.compiled:
                _refresh(first, progress, started)
        for s in rest:
            s.start()
        for s in rest:
            if isinstance(s, ProcessShard):
                s.wait_ready(progress, started)

    def alive_workers(self) -> int:
        """Worker processes that can take work now."""
        return sum(1 for s in self.shards if isinstance(s, ProcessShard) and not s.gone)

    def worker_lost(self, shard: ProcessShard) -> None:
        """A worker process died: re-seed its robots elsewhere and start a new one.

        Called on the dead worker's receiving thread. Its robots move to the surviving worker
        with the fewest robots (or wait for the new process when none survives) and are
        re-seeded from their last published poses (:mod:`service.live.supervise`); their scans
        it never answered are reported dropped.
        """
        code = shard.process.exitcode if not shard.process.is_alive() else None
        if self._ends_with_the_service(shard, code):
            return
        sends: list[Shard] = []
        with self.lock:
            if self.stopping or shard.gone:
                return
            shard.gone = True
            self.workers_replaced += 1
            alive = [s for s in self.shards if isinstance(s, ProcessShard) and not s.gone]
            moved = [r for r, b in self.boxes.items() if b.shard is shard]
            for robot in moved:
                box = self.boxes[robot]
                lost = shard.inflight.pop(robot, []) + list(box.entries)
                box.entries.clear()
                box.scan, box.busy, box.queued = None, False, False
                target = min(alive, key=lambda s: s.robots) if alive else shard
                shard.robots -= 1
                target.robots += 1
                box.shard = target
                for e in lost:
                    if e.kind == "scan":
                        self.dropped += 1
                        self.on_drop(robot, e.stamp_ns, e.received_ns)
                seed = box.history.reseed(lost, self.clock)
                for e in seed:
                    self.on_seed(robot, e)
                    box.history.note_input(e)
                self.reseeded += bool(seed)
                box.entries.extend(seed)
                if box.entries and box.worth_a_batch():
                    box.queued = True
                    target.ready.append(robot)
            shard.ready.clear()
            shard.inflight.clear()
            shard.outbox.clear()
            shard.control.clear()
            shard.in_flight = 0
            shard.sending = False
            for maps in self._maps.values():  # the new worker's engine needs every map
                shard.control.extend(maps)
            sends = [s for s in alive if s.wake()]
        for s in sends:
            s.drain()
        log.error(
            "worker process %d died (exit code %s): %d robots re-seeded from their last poses",
            shard.index,
            code,
            len(moved),
        )
        self.on_lost(shard.index, code, moved)
        shard.respawn()
        try:
            shard.wait_ready(None, time.monotonic())
        except RuntimeError:
            log.exception("the replacement of worker %d failed", shard.index)
            return
        with self.lock:
            shard.gone = False
            send = shard.wake()
        if send:
            shard.drain()

    def _ends_with_the_service(self, shard: ProcessShard, code: int | None) -> bool:
        """Whether a worker that ended with ``code`` ended with the service
        (:mod:`service.live.stopping`): then it is neither replaced nor reported lost, and the
        scans it never answered are reported dropped, as on a loss."""
        if self.stopping:
            return False  # the service stops it: worker_lost has nothing to do
        if code is None:
            shard.process.join(0.2)  # its pipe ended a moment before the process
            code = shard.process.exitcode
        if not ended_with_the_service(code, self.stop_requested):
            return False
        log.info("worker process %d ended (exit code %s) with the service", shard.index, code)
        with self.lock:
            shard.gone = True  # the service's stop waits for nothing more of it
            for robot, box in self.boxes.items():
                if box.shard is shard:  # what it never answered is dropped, as on a loss
                    for e in shard.inflight.pop(robot, []) + list(box.entries):
                        if e.kind == "scan":
                            self.dropped += 1
                            self.on_drop(robot, e.stamp_ns, e.received_ns)
                    box.entries.clear()
                    box.scan, box.busy, box.queued = None, False, False
            shard.cond.notify_all()
        return True

    def forget(self, robot: str) -> bool:
        """Drop an idle robot's mailbox and its state in the worker.

        Returns:
            ``False`` when the robot has inputs queued or in flight (it is not idle).
        """
        with self.lock:
            box = self.boxes.get(robot)
            if box is None:
                return True
            if box.busy or box.queued:
                return False
            # What waits is odometry alone (not worth a batch): it would change nothing
            # that is published before the robot's state goes.
            del self.boxes[robot]
            box.shard.robots -= 1
            box.shard.control.append(("forget", robot))
            send = box.shard.wake()
        if send:
            box.shard.drain()
        return True

    def idle_since(self, before_ns: int, placed: bool = True) -> list[str]:
        """Robots whose last input was received before ``before_ns``; with ``placed`` false,
        only those never placed (no InitialPose, Relocalize or seed taken in)."""
        with self.lock:
            return [
                r
                for r, b in self.boxes.items()
                if b.last_in < before_ns and (placed or not b.placed)
            ]

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
                live = [s for s in self.shards if not s.gone] or self.shards
                shard = min(live, key=lambda s: s.robots)
                shard.robots += 1
                box = self.boxes[robot] = Mailbox(shard)
            box.last_in = received_ns
            box.placed = box.placed or kind in PLACING
            if kind != "scan" and self.processes:
                box.history.note_input(entry)
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
        # Worker processes get the payload (a copy of bytes, not a GeoJSON walk under this
        # lock) and build the map when a robot first needs it (service.prepared).
        source: Any = loaded.world if not self.processes else loaded.payload
        msg = ("map", loaded.map_id, loaded.version, source, loaded.received_ns)
        if self.processes:
            self._maps.setdefault(loaded.map_id, deque(maxlen=_MAP_VERSIONS_SENT)).append(msg)
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
            if isinstance(s, ProcessShard):
                s.stop(deadline)
        for s in self.shards:
            s.join(max(deadline - time.monotonic(), 0.1))


def _once(progress: Callable[[str], None] | None) -> Callable[[str], None] | None:
    """``progress``, but each message passed on once only."""
    if progress is None:
        return None
    said: set[str] = set()
    told = progress

    def once(message: str) -> None:
        if message not in said:
            said.add(message)
            told(message)

    return once


def _refresh(shard: ProcessShard, progress: Callable[[str], None] | None, started: float) -> None:
    """Replace a worker that compiled the localizer's kernels, before it has any work, by one
    that loads them from numba's cache (in a second), and wait until it is ready: a process that
    compiled keeps the compiler's memory, about 130 MB, for as long as it runs
    (:func:`rlutf.warmup.compiled_here`)."""
    shard.generation += 1  # its receiving thread ends with it, and replaces nothing
    send(shard.conn, ("stop",))
    shard.process.join(30.0)
    if shard.process.is_alive():
        shard.process.terminate()
    shard.compiled = False
    shard.respawn()
    shard.wait_ready(progress, started)
