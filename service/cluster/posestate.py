"""The durable pose state: each robot's last published pose kept on disk, for restarts.

When every instance restarts (``kill -9``, an upgrade, a node reboot), no one on the bus knows
the robots' poses any more. :class:`PoseState` keeps, per robot, the last PoseEstimate this
instance published, when it published it (service clock, ns) and the robot's odometry readings
around the pose's stamp, and writes them to one JSON file every ``interval_s`` when something
changed, and once more at an orderly close. At the next start the file is read back and handed
to :meth:`service.cluster.ownership.Ownership.restore`: a robot's first input after the restart
then seeds it from that pose exactly as a handover does, the odometry reading at the pose's
stamp anchoring the motion the robot made while the service was down.

The file, ``{folder}/poses.json`` (:data:`FILE_NAME`)::

    {"version": 1, "instance": "host-1234", "written_ns": 1732300000123456789,
     "robots": {"r1": {"pose": {<PoseEstimate>}, "published_ns": 1732300000120000000,
                       "odom": [{<Odometry>}, ...]}}}

It is written atomically (temporary file, fsync, rename, fsync of the folder), so a crash leaves
the previous snapshot or the new one. Several instances may share a folder (compose replicas on
one named volume): a write merges with what the file holds under an advisory lock, keeping each
robot's entry with the newest pose stamp, so one instance never erases another's robots.

The hot path is two methods called by the service's main process: :meth:`PoseState.odom` per
odometry reading and :meth:`PoseState.pose` per published pose. Each is a dict look-up and an
append or assignment of references to bytes it already has; decoding and JSON work happen on
the writer thread.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from schemas import EventCode, Odometry, PoseEstimate, SchemaError, decode
from service.infile import replace_durably

log = logging.getLogger(__name__)

#: Version of the file's layout.
STATE_VERSION = 1
#: The state file's name inside the state folder.
FILE_NAME = "poses.json"
#: Odometry readings kept in memory per robot: enough to reach back past the newest pose's
#: stamp when a snapshot is taken (a pose is at most a scan period plus its latency old, ~0.15 s;
#: 32 readings span 0.32 s at 100 Hz).
ODOM_RING = 32
#: Largest state file read, bytes (200 robots take ~200 KB).
MAX_FILE_BYTES = 64 * 1024 * 1024


class StateUnreadable(ValueError):
    """The state file exists but cannot be used (not JSON, wrong layout, unreadable)."""


@dataclass(frozen=True)
class RestoredRobot:
    """One robot's entry of a state file.

    Attributes:
        pose: the last pose published for the robot.
        published_ns: when it was published, service clock (ns since the epoch).
        odometry: readings around the pose's stamp, oldest first.
    """

    pose: PoseEstimate
    published_ns: int
    odometry: tuple[Odometry, ...]


# ---------------------------------------------------------------------------- the format
def parse_state(data: bytes, max_bytes: int = 1_000_000) -> tuple[dict[str, RestoredRobot], int]:
    """Read a state file's bytes.

    Entries that do not validate are skipped (and logged): one bad robot does not cost the
    others their state.

    Args:
        data: the file's content.
        max_bytes: largest accepted pose or odometry payload.

    Returns:
        The valid entries by robot id, and how many entries were skipped.

    Raises:
        StateUnreadable: not JSON, or not the layout above.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as err:
        raise StateUnreadable(f"not JSON: {err}") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("robots"), dict):
        raise StateUnreadable("no 'robots' object at the top level")
    if doc.get("version") != STATE_VERSION:
        raise StateUnreadable(f"version {doc.get('version')!r}, expected {STATE_VERSION}")
    robots: dict[str, RestoredRobot] = {}
    skipped = 0
    for robot, entry in doc["robots"].items():
        try:
            robots[robot] = _entry(robot, entry, max_bytes)
        except (SchemaError, TypeError, KeyError, ValueError) as err:
            log.warning("state entry of robot %r skipped: %s", robot, err)
            skipped += 1
    return robots, skipped


def _entry(robot: str, entry: Any, max_bytes: int) -> RestoredRobot:
    pose = decode(PoseEstimate, json.dumps(entry["pose"]).encode(), max_bytes=max_bytes)
    if pose.robot_id != robot:
        raise ValueError(f"pose of robot {pose.robot_id!r} under {robot!r}")
    published = entry["published_ns"]
    if not isinstance(published, int) or isinstance(published, bool):
        raise TypeError(f"published_ns {published!r} is not an integer")
    odometry = tuple(
        decode(Odometry, json.dumps(o).encode(), max_bytes=max_bytes) for o in entry["odom"]
    )
    return RestoredRobot(pose, published, tuple(sorted(odometry, key=lambda o: o.stamp_ns)))


def odometry_around(
    readings: list[tuple[int, bytes]], stamp_ns: int, keep: int = 3
) -> list[tuple[int, bytes]]:
    """The readings that anchor odometry at ``stamp_ns``: the newest at or before it, the one
    before that and the first after it (for interpolation); the oldest after it when none is
    at or before.

    Args:
        readings: ``(stamp_ns, payload)``, oldest first.
        stamp_ns: the pose's stamp.
        keep: most readings returned.
    """
    before = [i for i, (stamp, _) in enumerate(readings) if stamp <= stamp_ns]
    if not before:
        return readings[:1]
    at = before[-1]
    start = max(0, at - (keep - 2)) if keep >= 2 else at
    return readings[start : at + 2][:keep]


def _stamp(entry: Any) -> int:
    """The pose stamp of a file entry; -1 when it has none."""
    try:
        stamp = entry["pose"]["stamp_ns"]
    except (KeyError, TypeError):
        return -1
    return stamp if isinstance(stamp, int) else -1


# ---------------------------------------------------------------------------- the keeper
class PoseKeeper(Protocol):
    """What the service calls: :class:`PoseState`, or :class:`NullPoseState` when off."""

    def open(self) -> tuple[list[RestoredRobot], list[str]]:
        """Read the state; start writing. Returns the robots and the problems found."""

    def odom(self, robot: str, stamp_ns: int, payload: bytes) -> None:
        """An odometry reading of a robot localized here (hot path)."""

    def forget(self, robot: str) -> None:
        """Drop a robot (evicted): no longer kept nor written."""

    def pose(self, robot: str, payload: bytes, stamp_ns: int, published_ns: int) -> None:
        """A pose published for a robot (hot path)."""

    def close(self) -> None:
        """Write a final snapshot and stop."""

    def figures(self) -> dict[str, object]:
        """Figures for the health message."""


class NullPoseState:
    """No durable state (``--no-state``)."""

    def open(self) -> tuple[list[RestoredRobot], list[str]]:
        """Nothing to read."""
        return [], []

    def odom(self, robot: str, stamp_ns: int, payload: bytes) -> None:
        """Nothing kept."""

    def forget(self, robot: str) -> None:
        """Nothing kept."""

    def pose(self, robot: str, payload: bytes, stamp_ns: int, published_ns: int) -> None:
        """Nothing kept."""

    def close(self) -> None:
        """Nothing to write."""

    def figures(self) -> dict[str, object]:
        """No figures."""
        return {}


class PoseState:
    """Keeps the robots' last poses and writes them to ``folder / FILE_NAME``.

    Args:
        folder: the state folder; created at :meth:`open`.
        instance: this instance's name (written in the file, for people reading it).
        interval_s: seconds between two snapshots (only when a pose changed).
        clock: the service clock, ns since the epoch.
        max_bytes: largest accepted payload when reading the file back.
        report: ``(level, code, message)``: an Event on ``{prefix}/events`` when writes start
            failing (``state_write_failed``) and when one succeeds again
            (``state_write_resumed``); without it, log lines say the same.
    """

    def __init__(
        self,
        folder: Path,
        instance: str,
        interval_s: float,
        clock: Callable[[], int],
        max_bytes: int = 1_000_000,
        report: Callable[[str, str, str], None] | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.path = self.folder / FILE_NAME
        self.instance = instance
        self.interval_s = interval_s
        self._clock = clock
        self._max_bytes = max_bytes
        # Written by the main process's threads, read by the writer: only whole references are
        # swapped in (a dict item, a deque append), which is safe under the GIL.
        self._poses: dict[str, tuple[bytes, int, int]] = {}
        self._rings: dict[str, deque[tuple[int, bytes]]] = {}
        self._dirty = False
        self._entries: dict[str, dict[str, Any]] = {}  # what the file held, by robot
        self._rendered: dict[str, tuple[bytes, dict[str, Any]]] = {}
        self._written_inode: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._write_lock = threading.Lock()
        self.writes = 0
        self.write_errors = 0
        self.last_written_ns = 0
        self._report = report
        self._failing: tuple[float, int] | None = None  # since (monotonic), errors then

    # ------------------------------------------------------------------------ lifecycle
    def open(self) -> tuple[list[RestoredRobot], list[str]]:
        """Read the state file and start the writer thread.

        Never raises: a missing file is an empty state; a corrupt one, or a folder that cannot
        be created, is reported in the returned problems and the service starts without it.

        Returns:
            The robots read back, and one message per problem found.
        """
        problems: list[str] = []
        robots: dict[str, RestoredRobot] = {}
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            with self._locked():  # a sharing instance may be writing its temporary file
                for stale in self.folder.glob(f".{FILE_NAME}.*.tmp"):  # cut short by a crash
                    stale.unlink(missing_ok=True)
            robots = self._read(problems)
        except OSError as err:
            problems.append(f"state folder {self.folder}: {err}")
        for problem in problems:
            log.warning("pose state: %s", problem)
        if robots:
            log.info("pose state: %d robots read back from %s", len(robots), self.path)
        self._thread = threading.Thread(target=self._run, name="rlutf-posestate", daemon=True)
        self._thread.start()
        return list(robots.values()), problems

    def _read(self, problems: list[str]) -> dict[str, RestoredRobot]:
        try:
            with self.path.open("rb") as f:
                data = f.read(MAX_FILE_BYTES + 1)
        except FileNotFoundError:
            return {}
        if len(data) > MAX_FILE_BYTES:
            problems.append(f"{self.path}: larger than {MAX_FILE_BYTES} bytes; not read")
            return {}
        try:
            robots, skipped = parse_state(data, self._max_bytes)
        except StateUnreadable as err:
            problems.append(f"{self.path} is unreadable ({err}); starting with no pose state")
            return {}
        if skipped:
            problems.append(f"{self.path}: {skipped} invalid robot entries skipped")
        return robots

    def close(self) -> None:
        """Stop the writer and write a last snapshot (call after the last pose is out)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
        self.write()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.write()

    # ------------------------------------------------------------------------ hot path
    def odom(self, robot: str, stamp_ns: int, payload: bytes) -> None:
        """Keep an odometry reading of a robot localized here (no decoding)."""
        ring = self._rings.get(robot)
        if ring is None:
            ring = self._rings[robot] = deque(maxlen=ODOM_RING)
        ring.append((stamp_ns, payload))

    def forget(self, robot: str) -> None:
        """Drop a robot's readings and pose (evicted; left out of the next snapshot)."""
        self._rings.pop(robot, None)
        if self._poses.pop(robot, None) is not None:
            self._dirty = True

    def pose(self, robot: str, payload: bytes, stamp_ns: int, published_ns: int) -> None:
        """Keep a pose published for ``robot`` (its encoded PoseEstimate)."""
        self._poses[robot] = (payload, stamp_ns, published_ns)
        self._dirty = True

    # ------------------------------------------------------------------------ writing
    def write(self) -> bool:
        """Write a snapshot if a pose changed since the last one.

        Returns:
            Whether a file was written. Errors are logged and counted, never raised: the
            service runs on without a durable state rather than stop.
        """
        with self._write_lock:
            if not self._dirty:
                return False
            self._dirty = False
            try:
                # The folder is made at open only: one gone since (a volume unmounted) is a
                # failed write, not a new folder on the disk beneath the mount point.
                with self._locked():
                    self._merge_file()
                    for robot, entry in self._own_entries().items():
                        if _stamp(entry) >= _stamp(self._entries.get(robot)):
                            self._entries[robot] = entry
                    self._replace(self._render())
            except OSError as err:
                self._dirty = True  # try again at the next interval
                self.write_errors += 1
                if self._failing is None:
                    self._failing = (time.monotonic(), self.write_errors - 1)
                    self._say(
                        "error",
                        EventCode.STATE_WRITE_FAILED,
                        f"pose state: cannot write {self.path} ({err}): the robots' poses are "
                        "not kept for a restart until it can write again (tried every "
                        f"{self.interval_s:g} s)",
                    )
                elif self.write_errors % 60 == 0:
                    log.warning("pose state: cannot write %s: %s", self.path, err)
                return False
            self.writes += 1
            if self._failing is not None:
                since, before = self._failing
                self._failing = None
                self._say(
                    "warning",
                    EventCode.STATE_WRITE_RESUMED,
                    f"pose state: written again to {self.path} after "
                    f"{time.monotonic() - since:.1f} s and {self.write_errors - before} failed "
                    "writes",
                )
            return True

    def _say(self, level: str, code: str, message: str) -> None:
        """An Event through ``report`` (which logs it too), else a log line."""
        if self._report is not None:
            self._report(level, code, message)
        else:
            log.warning("%s", message)

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """Hold the folder's advisory lock: instances sharing it write one at a time."""
        fd = os.open(self.folder / f".{FILE_NAME}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # releases the lock

    def _merge_file(self) -> None:
        """Take in the entries another instance wrote since this one's last write."""
        try:
            inode = self.path.stat().st_ino
        except FileNotFoundError:
            return
        if inode == self._written_inode:
            return  # the file is ours: nothing new in it
        try:
            doc = json.loads(self.path.read_bytes())
            theirs = doc["robots"]
            assert isinstance(theirs, dict)
        except (ValueError, KeyError, TypeError, AssertionError, UnicodeDecodeError):
            return  # unreadable: overwritten with ours (open() reported it)
        for robot, entry in theirs.items():
            if _stamp(entry) > _stamp(self._entries.get(robot)):
                self._entries[robot] = entry

    def _own_entries(self) -> dict[str, dict[str, Any]]:
        out: dict[str, dict[str, Any]] = {}
        for robot, (payload, stamp, published) in list(self._poses.items()):
            cached = self._rendered.get(robot)
            if cached is not None and cached[0] is payload:
                out[robot] = cached[1]  # unchanged since the last snapshot
                continue
            ring = self._rings.get(robot)
            readings = sorted(ring.copy() if ring is not None else (), key=lambda r: r[0])
            entry = {
                "pose": json.loads(payload),
                "published_ns": published,
                "odom": [json.loads(p) for _, p in odometry_around(readings, stamp)],
            }
            self._rendered[robot] = (payload, entry)
            out[robot] = entry
        return out

    def _render(self) -> bytes:
        now = self._clock()
        doc = {
            "version": STATE_VERSION,
            "instance": self.instance,
            "written_ns": now,
            "robots": dict(sorted(self._entries.items())),
        }
        self.last_written_ns = now
        return json.dumps(doc, separators=(",", ":")).encode()

    def _replace(self, data: bytes) -> None:
        """Write atomically: a crash leaves the old file or the new one."""
        replace_durably(self.path, data, f".{FILE_NAME}.")
        self._written_inode = self.path.stat().st_ino

    def figures(self) -> dict[str, object]:
        """Figures for the health message."""
        return {
            "state_writes": self.writes,
            "state_write_errors": self.write_errors,
            # Whether writes fail now (the errors above are counted for ever).
            "state_write_failing": self._failing is not None,
            "state_written_ns": self.last_written_ns,
        }
