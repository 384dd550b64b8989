"""The worker processes' side of the dispatcher: the pipe protocol and the loop that runs batches.

A worker process holds a :class:`~service.engine.FleetEngine` for the robots the dispatcher gave
it. The main process sends pickled tuples over a pipe: ``("map", ...)``, ``("batch", robot,
[(kind, payload, received_ns), ...])``, ``("forget", robot)``, ``("stop",)``, or ``("many",
[those])``; the worker says ``("ready", compiled)`` once its kernels are compiled (``compiled``
true: numba's cache did not hold them) or loaded, answers each batch with ``("done", robot,
outputs, compute_s)``, and ``("stopped",)``.
"""

from __future__ import annotations

import gc
import logging
import os
import pickle
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from multiprocessing.connection import Connection
from typing import Any

from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World
from rlutf.warmup import warm_up
from schemas import Map, SchemaError, decode
from service.engine import FleetEngine, Outbound
from service.guard import Limits
from service.keys import MODELS, InputKind, Keys, Message
from service.live.memory import HeapTrimmer
from service.maphealth import NullEvidence, ScanEvidence

log = logging.getLogger(__name__)

#: The GIL's switch interval in worker processes, seconds (Python's default: 0.005). While a
#: long update runs beside the ordinary ones, an ordinary update that comes back from a compiled
#: kernel waits up to this long for the GIL each time; at 5 ms the other robots' p99 latency
#: doubled in ``bench.relocalize_fleet``. Without a long update only one thread computes.
_SWITCH_INTERVAL_S = 0.0005
#: Garbage collector thresholds of the service's processes (Python's default: 700, 10, 10).
_GC_THRESHOLDS = (20_000, 20, 20)


@dataclass(eq=False)  # compared by identity: a mailbox removes the one it holds, fast
class Entry:
    kind: InputKind
    payload: bytes
    message: Message | None
    received_ns: int
    stamp_ns: int = 0


def send(conn: Connection, msg: tuple[Any, ...]) -> None:
    """Send over a worker pipe: ``Connection.send`` builds a new ForkingPickler per message,
    which costs more than the pickling of a batch."""
    conn.send_bytes(pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))


def recv(conn: Connection) -> Any:
    return pickle.loads(conn.recv_bytes())


def waiting(conn: Connection) -> bool:
    """Whether a message waits in the pipe (``False`` once it is closed)."""
    try:
        return conn.poll(0)
    except (EOFError, OSError):
        return False


def run_batch(engine: FleetEngine, robot: str, entries: list[Entry]) -> list[Outbound]:
    outputs: list[Outbound] = []
    for e in entries:
        msg = e.message
        if msg is None:
            try:
                msg = decode(MODELS[e.kind], e.payload)
            except SchemaError:  # validated at the callback; only a bug gets here
                log.exception("undecodable %s for %s reached a worker", e.kind, robot)
                continue
        try:
            outputs += engine.handle(robot, msg, e.received_ns)
        except Exception:  # one robot's failure must not take the worker down
            log.exception("update of %s failed", robot)
    return outputs


def evidence(map_health: bool) -> ScanEvidence:
    """Where an engine counts map health evidence: a grid per map, or nowhere."""
    return ScanEvidence() if map_health else NullEvidence()


class HandOver:
    """Appends the engine's map health evidence to a batch's outputs, at most once a second
    (:mod:`service.maphealth`): the main process merges it and publishes the MapHealth."""

    def __init__(self, engine: FleetEngine, interval_s: float = 1.0) -> None:
        self.engine = engine
        self.interval_s = interval_s
        self._next = time.monotonic() + interval_s
        self._lock = threading.Lock()

    def __call__(self, outputs: list[Outbound]) -> None:
        now = time.monotonic()
        with self._lock:
            if now < self._next:
                return
            self._next = now + self.interval_s
        handed = self.engine.hand_over()
        if handed is not None:
            outputs.append(handed)


def apply_control(engine: FleetEngine, msg: tuple[Any, ...]) -> None:
    if msg[0] == "forget":
        engine.forget(msg[1])
    elif msg[0] == "map":
        _, map_id, version, payload_or_world, received_ns = msg
        # A payload is built by the first update that needs it (service.prepared), not here on
        # the pipe thread, where it would hold up every robot of this worker.
        w = (
            payload_or_world
            if isinstance(payload_or_world, World)
            else partial(world_of_payload, payload_or_world)
        )
        engine.register_map(map_id, version, w, received_ns)


def world_of_payload(payload: bytes) -> World:
    """The map of a Map payload the main process has already validated."""
    msg = decode(Map, payload, max_bytes=len(payload))
    return World.from_geojson(msg.geometry.model_dump(mode="python"))


def tune_gc() -> None:
    """Make garbage collection cheap for a process that handles a stream of messages.

    Every message allocates short-lived containers, and Python's default thresholds then run a
    full collection, which walks every object alive, every few hundred messages: about a sixth
    of the service's main process time at 250 scans/s. Objects alive now (modules, settings,
    maps) are frozen out of collections, and young collections run less often.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(*_GC_THRESHOLDS)
    log.debug(
        "garbage collection tuned: %d objects frozen, thresholds %s",
        gc.get_freeze_count(),
        _GC_THRESHOLDS,
    )


def worker_main(
    conn: Connection,
    prefix: str,
    config: LocalizerConfig,
    interval: int,
    threads: int,
    limits: Limits | None = None,
    map_health: bool = True,
    nice: int = 0,
) -> None:
    """Entry point of a worker process: apply batches until told to stop.

    This thread reads the pipe, applies maps in pipe order and runs the batches (never two of
    one robot at once: the shard sends a robot's next batch after its ``done``) itself,
    answering each as soon as it is done, so that the main process can send the next batches
    while this one computes the rest (answering a whole pipe message at once left the worker
    idle while the main process turned the answers round); batches that may take long
    (relocalizing or lost robots) run on a pool of ``threads - 1`` threads and answer alone
    (with ``threads`` 1, everything runs here, one batch at a time). A map is registered before
    any batch sent after it is read. Running batches here rather than on a pool thread saves a
    thread hand-off per scan.

    With ``nice``, the process runs that much nicer than the service: when the cores cannot keep
    up, the service's main process (the inputs, the drops it counts, the poses it publishes)
    takes the CPU it needs first, and what is left over is dropped, counted, in the robots'
    mailboxes (``worker_nice``; ``BENCHMARKS.md``, "Overload").
    """
    # Ctrl-C and a terminal's hang-up are the service's to handle: a terminal signals the whole
    # process group, and a worker that took it would die in the middle of a batch while the
    # service stops it in order (its pipe's "stop", after the batches in flight) anyway.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    if nice:
        os.nice(nice)
    compiled = warm_up()
    engine = FleetEngine(Keys(prefix), config, interval, limits, evidence(map_health))
    hand_over = HandOver(engine)
    tune_gc()
    sys.setswitchinterval(_SWITCH_INTERVAL_S)
    send_lock = threading.Lock()
    send(conn, ("ready", compiled))  # the kernels are compiled or loaded: it can localize

    def answer(msg: tuple[Any, ...]) -> None:
        try:
            with send_lock:
                send(conn, msg)
        except (OSError, ValueError):
            log.warning("results not sent: the service is gone")

    def run(robot: str, batch: list[tuple[InputKind, bytes, int]]) -> tuple[Any, ...]:
        entries = [Entry(k, p, None, r) for k, p, r in batch]
        t0 = time.perf_counter()
        outputs = run_batch(engine, robot, entries)
        hand_over(outputs)
        return ("done", robot, outputs, time.perf_counter() - t0)

    def run_and_answer(robot: str, batch: list[tuple[InputKind, bytes, int]]) -> None:
        answer(run(robot, batch))

    slow_lane = max(threads - 1, 0)
    trimmer = HeapTrimmer()
    with ThreadPoolExecutor(max(slow_lane, 1), thread_name_prefix="rlutf-long") as slow:
        while True:
            try:
                msg = recv(conn)
            except (EOFError, OSError, KeyboardInterrupt):
                return
            trimmer.maybe()
            for item in msg[1] if msg[0] == "many" else [msg]:
                kind = item[0]
                if kind == "stop":
                    slow.shutdown(wait=True)
                    answer(("stopped",))
                    return
                if kind in ("map", "forget"):
                    apply_control(engine, item)
                    continue
                _, robot, batch = item
                if slow_lane > 0 and engine.expects_long_update(robot, [e[0] for e in batch]):
                    slow.submit(run_and_answer, robot, batch)
                else:
                    answer(run(robot, batch))
