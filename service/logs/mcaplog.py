"""The MCAP recorder of the service: one writer thread fed by a bounded queue.

:meth:`McapRecorder.record` only enqueues: it never blocks and never raises. When the queue is
full the message is not recorded, :attr:`McapRecorder.overflowed` counts it, and once the queue
has drained the writer logs an Event with code ``recorder_overflow`` on ``{prefix}/events``
saying how many were lost. Everything else happens on the writer thread, a batch of messages at
a time: JSON Schema registration, chunking and zstd compression (:mod:`service.logs.mcapwriter`),
and the Foxglove views (:mod:`service.logs.foxglove`) when asked for (``foxglove=True``, the
setting ``record_views``). By default a live log holds the WIRE.md channels only: the views are
optional channels, and ``rlutf log views`` or ``rlutf replay`` write them from the log, off the
live service's main process (they cost it more than the rest of recording together).

Files are named ``rlutf[-{instance}]-{UTC start}-{n}.mcap`` in the record folder. A file is
written as ``NAME.mcap.part``, flushed (chunk closed, fsync) at least every ``flush_interval_s``
while messages come in, so a crash loses about that much; it is finished (summary, footer,
fsync) and renamed to ``NAME.mcap`` when it reaches ``max_bytes`` or ``max_seconds``, or when
the recorder closes. A ``.part`` file left by a crash is repaired by ``rlutf log recover``. A
file is opened at the first message after start or rotation; each file starts with the
``rlutf.config`` metadata and the newest version of every map seen so far (with its original
``log_time``), so every file opens in Foxglove with its map.

A write error (a full disk, the folder gone) never reaches the service: the file is left as it
is, an Event ``recording_failed`` is published, messages are counted (:attr:`McapRecorder.
unrecorded`) instead of logged, and a file is opened again every :data:`RETRY_S`; the first file
written and flushed after that starts with an Event ``recording_resumed`` that says how many
messages the gap holds, and the run's file numbers skip one there, so the log tools name the gap.

Every file also holds the ``rlutf.run`` metadata (:mod:`service.logs.runs`): the recorder's run id
(new for every recorder, that is every start of the service), the instance, when the recorder
started and the file's sequence number within the run (0, 1, 2 ... as files rotate; the number
in the file name counts from 1 and skips names already taken) and the number of the file opened
before it (``follows``), so the log tools can tell which files of a folder belong together, and
which numbers are recording gaps rather than files left out. As it finishes a file it writes the
``rlutf.manifest`` metadata (:mod:`service.logs.manifest`): the file's messages per topic and
whether the run ended with it; a run that stops with no file open (the last one rotated) ends
with a file of its maps alone, so that the run's end is in its files.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any, NamedTuple, cast

from schemas import Event, EventCode, encode
from service.logs.foxglove import FoxgloveConverter
from service.logs.mcapfile import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_ZSTD_LEVEL,
    LogWriter,
    Record,
    load_schemas,
)
from service.logs.partfile import check_in_place
from service.logs.recqueue import ConfigItem as _Config
from service.logs.recqueue import Item as _Item
from service.logs.recqueue import Message as _Message
from service.logs.recqueue import Queue as _Queue
from service.logs.recqueue import Stop as _Stop
from service.logs.runs import RUN_METADATA, RunTag, new_run_id

log = logging.getLogger(__name__)

PART_SUFFIX = ".part"
_MAP_SCHEMA = "rlutf.Map"
#: The open file's size and age are checked for rotation after this many seconds or this many
#: message bytes (uncompressed; at most a sixteenth of the size limit), whichever comes first.
_ROTATE_CHECK_S = 0.1
_ROTATE_CHECK_BYTES = 64 * 1024
#: After a write error, seconds before the recorder opens a file again (messages meanwhile are
#: counted, not logged): a full disk is not tried, and a file left empty, once per message.
RETRY_S = 5.0
#: The writer thread takes the queued messages this often, seconds (see :class:`_Queue`).
_POLL_S = 0.02


class _OpenFile(NamedTuple):
    part: Path
    final: Path
    stream: IO[bytes]
    writer: LogWriter
    opened: float  # time.monotonic()
    sequence: int = 0  # within the run
    follows: int | None = None  # the run's file opened before it


class McapRecorder:
    """Records the service's messages into rotated MCAP files (see the module docstring).

    Args:
        record_dir: folder of the logs; created if missing.
        max_bytes: rotate a file once it is this large.
        max_seconds: rotate a file this long after it was opened.
        queue_size: messages the queue holds; past that (or past :data:`LARGE_QUEUED` bytes of
            large messages) they are counted and dropped.
        instance: the service instance's name, put in file names (replicas may share a folder).
        flush_interval_s: longest time between two flushes of an open file.
        chunk_size: uncompressed bytes at which a chunk is closed early.
        zstd_level: the chunks' zstd level.
        foxglove: also log the Foxglove views (off: ``rlutf log views`` writes them later).

    Raises:
        service.logs.mcapfile.SchemaMissing: the installed package lacks a schema it may log.
    """

    def __init__(
        self,
        record_dir: Path | str,
        *,
        max_bytes: int = 256 * 1024 * 1024,
        max_seconds: float = 3600.0,
        queue_size: int = 20000,
        instance: str | None = None,
        flush_interval_s: float = 1.0,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        zstd_level: int = DEFAULT_ZSTD_LEVEL,
        foxglove: bool = False,
    ) -> None:
        self.record_dir = Path(record_dir)
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.max_bytes = max_bytes
        self.max_seconds = max_seconds
        self.queue_size = queue_size
        self.instance = instance
        self.flush_interval_s = flush_interval_s
        self.chunk_size = chunk_size
        self.zstd_level = zstd_level
        self._converter = FoxgloveConverter() if foxglove else None
        # read now, for every file of the run: a package reinstalled under the service cannot
        # change what it logs, and one that lacks a schema stops it at start
        self._known = load_schemas()
        self._queue = _Queue(queue_size, _POLL_S)
        self._lock = threading.Lock()
        self._overflowed = 0
        self._unreported = 0
        self._overflow_since_ns = 0  # the first message lost since the last overflow Event
        self._closed = False
        self._config: dict[str, Any] | None = None
        self._maps: dict[str, Record] = {}
        self._unchecked = 0  # message bytes written since the last rotation check
        self._file: _OpenFile | None = None
        self._sequence = 0
        self._opened = 0  # files opened: the next file's sequence number within the run
        self._previous: int | None = None  # the sequence number of the file opened last
        self.run_id = new_run_id()
        """This recorder's run (``rlutf.run`` metadata of every file it writes)."""
        self.started_ns = time.time_ns()
        """When the run started, ns since the epoch."""
        self.files: list[Path] = []
        """Finished files, oldest first."""
        self.errors = 0
        """Write errors (the first of a series is an Event ``recording_failed``)."""
        self.on_event: Callable[[Event], None] | None = None
        """Called (on the writer thread) with each of the recorder's own Events
        (``recorder_overflow``, ``recording_failed``, ``recording_resumed``), e.g. to publish
        it; it must not call :meth:`record` with it (it is logged already, when it can be)."""
        self._failing: tuple[float, int] | None = None  # since (monotonic), time_ns
        self._retry_at = 0.0
        self.unrecorded = 0
        """Messages not logged because the recorder could not write (see :data:`RETRY_S`)."""
        self._unrecorded_now = 0  # since the failure being reported
        self._thread = threading.Thread(target=self._run, name="rlutf-recorder", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ any thread
    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Queue one message; never blocks and never raises on a full queue."""
        if self._closed:
            return
        if type(payload) is not bytes:
            payload = bytes(payload)
        if not self._queue.put_nowait((topic, schema_name, payload, log_time_ns, publish_time_ns)):
            with self._lock:
                self._overflowed += 1
                if not self._unreported:
                    self._overflow_since_ns = log_time_ns
                self._unreported += 1

    def set_config(self, config: dict[str, Any]) -> None:
        """Store the effective configuration as ``rlutf.config`` metadata in every file."""
        if self._closed:
            return
        # Never dropped (called once at start-up).
        self._queue.put(_Config(dict(config)))

    @property
    def overflowed(self) -> int:
        """Messages not recorded because the queue was full."""
        return self._overflowed

    @property
    def queued(self) -> int:
        """Messages (and control items) waiting for the writer thread; read without a lock."""
        return len(self._queue)

    @property
    def current_path(self) -> Path | None:
        """The ``.part`` file being written, if any."""
        f = self._file
        return f.part if f is not None else None

    def close(self, timeout: float = 30.0) -> None:
        """Write what is queued, finish the open file and stop the writer thread."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + timeout
        self._queue.put(_Stop())
        self._thread.join(max(deadline - time.monotonic(), 0.1))
        if self._thread.is_alive():
            log.error("recorder did not finish within %.0f s", timeout)

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval_s
        next_rotate_check = 0.0
        while True:
            batch = self._queue.take(max(next_flush - time.monotonic(), 0.0))
            stopped = self._write(batch)
            try:
                if self._unreported and self._queue.empty():
                    self._report_overflow()
                now = time.monotonic()
                if now >= next_flush:
                    self._flush()
                    next_flush = now + self.flush_interval_s
                    if self._failing is not None and self._file is not None:
                        self._resumed()  # a file was written and flushed again
                if now >= next_rotate_check:
                    # Not after every message: the size check is a system call.
                    self._unchecked = 0
                    self._maybe_rotate()
                    next_rotate_check = now + _ROTATE_CHECK_S
            except Exception:  # a full disk must not stop the service
                self._failed()
            if stopped:
                break
        try:
            if self._unreported:
                self._report_overflow()
            self._end_run()
        except Exception:
            self.errors += 1
            log.exception("finishing the log failed")

    def _write(self, batch: list[_Item]) -> bool:
        """Write a batch of queued items; whether it ended with the stop."""
        check_bytes = min(_ROTATE_CHECK_BYTES, self.max_bytes // 16)
        converts = self._converter is not None
        for item in batch:
            try:
                if type(item) is tuple:  # a message (not a NamedTuple): the hot path
                    message = cast(_Message, item)
                    topic, schema_name, payload, log_time_ns, _ = message
                    f = self._file
                    if f is None and self._failing is not None and not self._retry():
                        if schema_name == _MAP_SCHEMA:  # the next file still starts with it
                            self._maps[topic] = Record(*message)
                        self.unrecorded += 1
                        self._unrecorded_now += 1
                        continue
                    # Before latching: a new file starts with the maps seen before.
                    writer = f.writer if f is not None else self._writer(log_time_ns)
                    if schema_name == _MAP_SCHEMA:
                        self._maps[topic] = Record(*message)
                    if converts:
                        writer.write(Record(*message))
                    else:
                        writer.add(*message)
                    self._unchecked += len(payload)
                    if self._unchecked >= check_bytes:
                        self._unchecked = 0
                        self._maybe_rotate()
                elif isinstance(item, _Config):
                    self._config = item.config
                    if self._file is not None:
                        self._file.writer.write_config(item.config)
                else:
                    return True
            except Exception:  # a full disk must not stop the service
                self._failed()
        return False

    def _failed(self) -> None:
        """A write failed: the file is left as it is (an empty one removed), and no file is
        opened for :data:`RETRY_S`; the first failure of a series is logged and reported."""
        self.errors += 1
        f = self._file
        self._abandon()
        if f is not None:
            with contextlib.suppress(OSError):
                if f.part.stat().st_size == 0:
                    f.part.unlink()
                    self._sequence -= 1  # its number goes to the next file that opens
                    self._opened = f.sequence  # and its number in the run
                    self._previous = f.follows  # and the run's next file follows the one before
        self._retry_at = time.monotonic() + RETRY_S
        if self._failing is not None:
            log.debug("recording failed again", exc_info=True)
            return
        log.debug("recording failed", exc_info=True)  # the Event below says why, in one line
        self._failing = (time.monotonic(), time.time_ns())
        self._opened += 1  # a number for the stretch not logged: the log tools name it missing
        self._unrecorded_now = 0
        err = sys.exc_info()[1]
        self._report(
            "error",
            EventCode.RECORDING_FAILED,
            f"recording to {self.record_dir} failed ({err}): messages are not "
            f"logged until it can write again (tried every {RETRY_S:g} s)",
            logged=False,
        )

    def _retry(self) -> bool:
        """Whether to open a file again after a failure."""
        return time.monotonic() >= self._retry_at

    def _resumed(self) -> None:
        assert self._failing is not None
        since, since_ns = self._failing
        self._failing = None
        lost, self._unrecorded_now = self._unrecorded_now, 0
        self._report(
            "warning",
            EventCode.RECORDING_RESUMED,
            f"recording resumed after {time.monotonic() - since:.1f} s: {lost} "
            f"messages were not logged since {datetime.fromtimestamp(since_ns / 1e9, UTC)}",
            stamp=since_ns,  # the gap began then: replay audits the poses before it
        )

    def _prefix(self) -> str:
        return str((self._config or {}).get("prefix", "rlutf"))

    def _about(self) -> str:
        return f"{self._prefix()}/service/{self.instance}" if self.instance else ""

    def _report(
        self, level: str, code: str, message: str, logged: bool = True, stamp: int | None = None
    ) -> None:
        """An Event of the recorder's own on ``{prefix}/events`` (stamped ``stamp``, default
        now): in the MCAP log (``logged``), handed to :attr:`on_event` (which logs it in the
        service's log), else in the service's log here."""
        now = time.time_ns()
        stamp = now if stamp is None else stamp
        event = Event(stamp_ns=stamp, level=level, code=code, key=self._about(), message=message)
        if self.on_event is None:
            log.log(logging.ERROR if level == "error" else logging.WARNING, "%s: %s", code, message)
        if logged:
            self._writer(now).write(
                Record(f"{self._prefix()}/events", "rlutf.Event", encode(event), now, stamp)
            )
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:
                log.exception("publishing the recorder's Event failed")

    def _writer(self, first_ns: int) -> LogWriter:
        """The open file's writer; a new file if none is open, whose first own message is
        logged at ``first_ns``."""
        if self._file is None:
            self._file = self._open()._replace(sequence=self._opened, follows=self._previous)
            writer = self._file.writer
            if self._config is not None:
                writer.write_config(self._config)
            tag = RunTag(
                self.run_id,
                self.instance or "",
                self.started_ns,
                self._opened,
                first_ns,
                self._previous,
            )
            self._previous = self._opened
            self._opened += 1
            writer.write_metadata(RUN_METADATA, tag.to_metadata())
            writer.write_all(self._maps.values())
        return self._file.writer

    def _open(self) -> _OpenFile:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        base = f"rlutf-{self.instance}" if self.instance else "rlutf"
        while True:
            self._sequence += 1
            final = self.record_dir / f"{base}-{stamp}-{self._sequence:03d}.mcap"
            part = final.with_name(final.name + PART_SUFFIX)
            if not final.exists() and not part.exists():
                break
        try:
            stream = open(part, "xb")  # noqa: SIM115 -- owned by _OpenFile until _finish
        except OSError:
            self._sequence -= 1  # a retry of a full disk or a folder gone takes no number
            raise
        writer = LogWriter(
            stream, self._converter, self.chunk_size, self.zstd_level, known=self._known
        )
        # each retry while recording fails opens a file: said once the file is written to
        (log.info if self._failing is None else log.debug)("recording to %s", part)
        return _OpenFile(part, final, stream, writer, time.monotonic())

    def _report_overflow(self) -> None:
        with self._lock:
            lost, self._unreported = self._unreported, 0
            since = self._overflow_since_ns
        self._report(
            "warning",
            EventCode.RECORDER_OVERFLOW,
            f"{lost} messages were not recorded: the recorder queue "
            f"({self.queue_size} messages) was full",
            logged=self._failing is None,
            # Stamped when the first was lost: the log lacks messages from then on, which replay
            # takes as a recording gap (it audits the poses before it).
            stamp=since or None,
        )

    def _flush(self) -> None:
        f = self._file
        if f is None:
            return
        check_in_place(f.part, f.stream.fileno())
        if not f.writer.dirty:
            return
        f.writer.flush()
        f.stream.flush()
        os.fsync(f.stream.fileno())

    def _maybe_rotate(self) -> None:
        f = self._file
        if f is None:
            return
        if f.stream.tell() >= self.max_bytes or time.monotonic() - f.opened >= self.max_seconds:
            self._finish()

    def _end_run(self) -> None:
        """Finish the open file as the run's last; with none open (the last one rotated, no
        message since), a file of the run's maps alone says where the run ended."""
        if self._file is None and self.files and self._failing is None:
            self._writer(time.time_ns())
        self._finish(last=True)

    def _finish(self, last: bool = False) -> None:
        f = self._file
        if f is None:
            return
        if self._failing is not None:  # opened again after a failure, not flushed yet
            self._resumed()  # the gap is marked in the file before it is finished
        self._file = None
        try:
            f.writer.write_manifest(self.run_id, f.sequence, last)
            f.writer.finish()
            f.stream.flush()
            os.fsync(f.stream.fileno())
        finally:
            f.stream.close()
        os.replace(f.part, f.final)
        _fsync_dir(f.final.parent)
        self.files.append(f.final)
        log.info("finished %s", f.final)

    def _abandon(self) -> None:
        """After a write error: close the file as it is (``rlutf log recover`` repairs it)."""
        f = self._file
        self._file = None
        if f is not None:
            with contextlib.suppress(OSError):
                f.stream.close()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
