"""The shards that run robots' batches: threads of this process, or a worker process each.

A shard holds a queue of ready robots; the :class:`~service.live.dispatch.Dispatcher` fills it
and the shard hands each robot's batch to a thread (:class:`ThreadShard`) or through a pipe to
its worker process (:class:`ProcessShard`, :mod:`service.live.worker`). A worker process says
when it is ready (its kernels compiled or loaded); when it dies, its receiving thread reads the
end of the pipe and has the dispatcher replace it (:meth:`Dispatcher.worker_lost`).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, Protocol

from rlutf.localizer import LocalizerConfig
from service.engine import FleetEngine, Outbound
from service.guard import Limits
from service.keys import Keys
from service.live.publishing import HOLD_S, PoseOut
from service.live.supervise import History
from service.live.warmaside import COMPILING
from service.live.worker import (
    Entry,
    HandOver,
    apply_control,
    evidence,
    recv,
    run_batch,
    send,
    waiting,
    worker_main,
)

log = logging.getLogger(__name__)

#: Batches a shard may have in flight at once (for different robots), so it never waits idle;
#: a shard runs them on as many threads, so a long update holds up only its own robot.
IN_FLIGHT = 4
#: The same for a worker process: robots whose batches are in its pipe or being computed.
PIPE_IN_FLIGHT = 16
#: Odometry readings a mailbox holds for a robot that sends no scan before they go anyway.
ODOM_ALONE = 32


@dataclass
class Mailbox:
    shard: Shard
    entries: deque[Entry] = field(default_factory=deque)
    scan: Entry | None = None  # the unprocessed scan in ``entries``, if any
    busy: bool = False
    queued: bool = False
    last_in: int = 0  # receive time of the robot's last input
    placed: bool = False  # an InitialPose or a Relocalize (a seed too) was taken in
    history: History = field(default_factory=History)  # to re-seed it if its worker dies

    def worth_a_batch(self) -> bool:
        """Whether the entries are worth sending to the worker now.

        Odometry alone changes nothing that is published: it waits in the mailbox for the
        robot's next scan or request (robots send odometry just before each scan, and sending
        it alone cost a second pipe round trip per scan), up to :data:`ODOM_ALONE` readings.
        """
        return (
            self.scan is not None
            or len(self.entries) >= ODOM_ALONE
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
OnSeed = Callable[[str, Entry], None]
"""Called (under the dispatcher's lock) with each input made to re-seed a robot, to record it."""
OnLost = Callable[[int, int | None, list[str]], None]
"""Called with a dead worker's index, its exit code and the robots it held."""


class Dispatcher(Protocol):
    """What a shard needs of the :class:`~service.live.dispatch.Dispatcher` that feeds it."""

    keys: Keys
    config: LocalizerConfig
    event_interval_ns: int
    threads: int
    limits: Limits
    map_health: bool
    nice: int
    poses: PoseOut | None
    lock: threading.Lock
    boxes: dict[str, Mailbox]
    stopping: bool

    def deliver(self, done: Done) -> None: ...

    def worker_lost(self, shard: ProcessShard) -> None: ...


class Shard:
    """A queue of ready robots served by one worker (process or thread)."""

    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        self.index = index
        self.dispatcher = dispatcher
        self.ready: deque[str] = deque()
        self.control: deque[tuple[Any, ...]] = deque()
        self.cond = threading.Condition(dispatcher.lock)
        self.in_flight = 0
        self.max_in_flight = max(IN_FLIGHT, dispatcher.threads)
        self.robots = 0  # robots assigned to this shard
        self.threads: list[threading.Thread] = []
        self.gone = False  # a dead worker process, until its replacement is ready

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


class ThreadShard(Shard):
    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        super().__init__(index, dispatcher)
        d = dispatcher
        self.engine = FleetEngine(
            d.keys, d.config, d.event_interval_ns, d.limits, evidence(d.map_health)
        )
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
            self._execute(robot, item)  # type: ignore[arg-type]

    def _execute(self, robot: str, entries: list[Entry]) -> None:
        """Run one batch, publish it, and mark the robot done."""
        d = self.dispatcher
        t0 = time.perf_counter()
        try:
            outputs = run_batch(self.engine, robot, entries)
            self.hand_over(outputs)
            # Published before the robot's next batch may start on another thread: its poses
            # go out (and into the log) in order.
            d.deliver(Done(robot, outputs, time.perf_counter() - t0))
        finally:
            with d.lock:
                self.finish(robot)
                self.cond.notify_all()


class LoopShard(ThreadShard):
    """The robots of a process whose inputs come in on one loop thread (:mod:`service.live.loop`).

    No thread of its own: the loop thread takes in what arrived, then calls :meth:`run_ready`,
    which runs every ready batch on that same thread, so an input costs no thread hand-off and
    no GIL hand-over between a callback thread and an update thread. Batches that may take long
    (relocalizing or lost robots: :meth:`FleetEngine.expects_long_update`) run on a pool of
    ``threads - 1`` threads instead, so that a relocalization holds up only its own robot, as
    in a worker process (:func:`service.live.worker.worker_main`).
    """

    def __init__(self, index: int, dispatcher: Dispatcher) -> None:
        super().__init__(index, dispatcher)
        d = dispatcher
        self.slow_lane = max(d.threads - 1, 0)
        self.pool = ThreadPoolExecutor(max(self.slow_lane, 1), thread_name_prefix="rlutf-long")
        self.max_in_flight = 1 << 30  # the loop runs what is ready; the pool queues its own

    def start(self) -> None:
        """Nothing to start: the loop thread runs the batches."""

    def join(self, timeout: float) -> None:
        self.run_ready()  # what was queued before the stop
        self.pool.shutdown(wait=True)

    def run_ready(
        self, until: float | None = None, after_batch: Callable[[], object] | None = None
    ) -> int:
        """Run the ready batches (long ones on the pool) until ``time.perf_counter()`` reaches
        ``until`` (checked after each batch: one runs at least), and apply control messages;
        ``after_batch`` is called after each batch run here.

        Returns:
            The batches started.
        """
        d = self.dispatcher
        started = 0
        while True:
            with d.lock:
                work = self.take()
                if work is not None and work[0] is None:
                    apply_control(self.engine, work[1])  # type: ignore[arg-type]
                    continue
            if work is None:
                return started
            robot, item = work
            assert robot is not None and isinstance(item, list)
            entries = item
            started += 1
            kinds: list[str] = [e.kind for e in entries]
            if self.slow_lane and self.engine.expects_long_update(robot, kinds):
                self.pool.submit(self._execute, robot, entries)
            else:
                self._execute(robot, entries)
                if after_batch is not None:
                    after_batch()
            if until is not None and time.perf_counter() >= until:
                return started


class ProcessShard(Shard):
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
        self.conn, self.process = self._spawn()
        self.ready_event = threading.Event()
        # The worker compiled the localizer's kernels (numba's cache did not hold them).
        self.compiled = False
        # Batches taken for the worker (in its pipe or being computed), by robot: what is lost
        # if the worker dies.
        self.inflight: dict[str, list[Entry]] = {}
        self.generation = 0
        # A worker runs its batches one after another, so it idles while the main process turns
        # its answers round; with only IN_FLIGHT batches in its pipe that round trip (a GIL
        # hand-off in the main process) capped a worker well under a core (measured: 150
        # robots, workers 28 % busy, 14 % of scans superseded). 16 batches of a few kB each
        # still fit the pipe's buffer.
        self.max_in_flight = max(PIPE_IN_FLIGHT, dispatcher.threads)
        self.outbox: list[tuple[Any, ...]] = []
        self.sending = False

    def _spawn(self) -> tuple[Connection, BaseProcess]:
        ctx = mp.get_context("spawn")
        conn, child = ctx.Pipe()
        d = self.dispatcher
        process = ctx.Process(
            target=worker_main,
            args=(
                child,
                d.keys.prefix,
                d.config,
                d.event_interval_ns,
                d.threads,
                d.limits,
                d.map_health,
                d.nice,
            ),
            name=f"rlutf-worker-{self.index}",
            daemon=True,
        )
        self._child: Connection | None = child
        return conn, process

    def start(self) -> None:
        self.process.start()
        if self._child is not None:
            # This process's copy of the worker's end: closed, so that the worker's death
            # reads as the end of the pipe here.
            self._child.close()
            self._child = None
        t = threading.Thread(
            target=self._recv,
            args=(self.conn, self.generation),
            name=f"rlutf-shard-{self.index}-recv",
            daemon=True,
        )
        self.threads.append(t)
        t.start()

    def take(self) -> tuple[str | None, tuple[Any, ...] | list[Entry]] | None:
        if self.gone:
            return None  # replaced: the new worker takes work once it is ready
        work = super().take()
        if work is not None and work[0] is not None:
            self.inflight[work[0]] = work[1]  # type: ignore[assignment]
        return work

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
                # The worker died: its receiving thread reads the end of the pipe and
                # replaces it (Dispatcher.worker_lost); what was not sent is re-seeded there.
                log.warning("worker %d is gone", self.index)

    def _recv(self, conn: Connection, generation: int) -> None:
        d = self.dispatcher
        poses = d.poses
        if poses is not None:
            poses.hold()  # the poses of the answers waiting in the pipe go out together
        try:
            while True:
                try:
                    msg = recv(conn)
                except (EOFError, OSError):
                    break
                if msg[0] == "stopped":
                    return
                if msg[0] == "ready":
                    self.compiled = len(msg) > 1 and bool(msg[1])
                    self.ready_event.set()
                    continue
                _, robot, outputs, compute_s = msg
                with d.lock:
                    self.inflight.pop(robot, None)
                    box = d.boxes.get(robot)
                    if box is not None:
                        for out in outputs:
                            if out.kind == "pose":
                                box.history.note_pose(out.payload, out.received_ns)
                    self.finish(robot)
                    send = self.wake()
                if send:
                    self.drain()  # the worker gets its next batches before we publish these
                d.deliver(Done(robot, outputs, compute_s))
                if poses is not None:
                    poses.release(HOLD_S if waiting(conn) else 0.0)
        finally:
            if poses is not None:
                poses.release()
        if not d.stopping and generation == self.generation:
            d.worker_lost(self)

    def respawn(self) -> None:
        """Start a new worker process in place of the dead one (maps are queued first)."""
        self.process.join(0.1)
        self.conn.close()
        self.generation += 1
        self.ready_event = threading.Event()
        self.conn, self.process = self._spawn()
        self.start()

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

    def wait_ready(self, progress: Callable[[str], None] | None, started: float) -> None:
        """Block until the worker can localize.

        Raises:
            RuntimeError: the worker process exited first.
        """
        said = False
        while not self.ready_event.wait(0.5):
            if not self.process.is_alive():
                raise RuntimeError(
                    f"worker process {self.index} exited with code {self.process.exitcode} "
                    "before it was ready"
                )
            waited = time.monotonic() - started
            if progress is not None and waited > 3.0 and not said:
                said = True
                progress(COMPILING)
