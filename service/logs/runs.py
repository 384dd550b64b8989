"""Runs: which log files belong together (WIRE.md v1.2, metadata ``rlutf.run``).

Every file the service's recorder or ``rlutf replay`` writes holds one ``rlutf.run`` metadata
record naming its run: ``run_id`` (new at every start of a service or a replay), ``instance``,
``started_ns`` (when the run started) and ``sequence`` (the file's number within the run: 0, 1,
2 ... as the recorder rotates). The recorder also writes ``opened_ns``: the ``log_time`` of the
first message of the file's own; a rotated file starts with the maps recorded before it, at
their original ``log_time``, and those are the maps logged before ``opened_ns``.

:func:`group_runs` sorts a list of files (a shell glob over a log folder matches several runs)
into runs, each with its files in sequence order; files without ``rlutf.run`` (written by
another tool) form one run of their own, in the order given. Replay and audit then treat each
run on its own, so no robot's state or map is carried from one run into another. A file with
none of rlutf's messages at all (a rosbag2 recording, say) is no run: replay names it
(:func:`foreign`) rather than pass an audit that read nothing.
"""

from __future__ import annotations

import itertools
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from service.infile import not_a_file
from service.logs.mcapread import LogError, LogFile, NotALog
from service.logs.partfile import left_unfinished

RUN_METADATA = "rlutf.run"
"""Name of the metadata record that names a file's run."""


class RunConflict(LogError):
    """Two different files claim the same place in the same run."""


@dataclass(frozen=True)
class RunTag:
    """The ``rlutf.run`` record of one file.

    Attributes:
        run_id: unique per start of a service or a replay.
        instance: the service instance (``replay`` for a replay's output).
        started_ns: when the run started, ns since the epoch.
        sequence: the file's number within the run, from 0.
        opened_ns: ``log_time`` of the file's first own message (``None``: not recorded);
            maps logged before it were carried over from the run's earlier files.
        follows: the sequence number of the run's file opened before this one (``None``: the
            first file, or not recorded); the numbers between were taken by no file (the
            recorder skips one where it could not write: a recording gap).
        extra: any other keys of the record (e.g. ``replayed_run``).
    """

    run_id: str
    instance: str
    started_ns: int
    sequence: int
    opened_ns: int | None = None
    follows: int | None = None
    extra: tuple[tuple[str, str], ...] = ()

    def to_metadata(self) -> dict[str, str]:
        """The record's data (MCAP metadata values are strings)."""
        data = {
            "run_id": self.run_id,
            "instance": self.instance,
            "started_ns": str(self.started_ns),
            "sequence": str(self.sequence),
        }
        if self.opened_ns is not None:
            data["opened_ns"] = str(self.opened_ns)
        if self.follows is not None:
            data["follows"] = str(self.follows)
        data.update(self.extra)
        return data

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> RunTag | None:
        """The tag in a record's data; ``None`` if ``run_id`` is missing or a number is not."""
        run_id = data.get("run_id")
        if not run_id:
            return None
        try:
            started = int(data.get("started_ns", "0"))
            sequence = int(data.get("sequence", "0"))
            opened = int(data["opened_ns"]) if "opened_ns" in data else None
            follows = int(data["follows"]) if "follows" in data else None
        except ValueError:
            return None
        known = {"run_id", "instance", "started_ns", "sequence", "opened_ns", "follows"}
        extra = tuple(sorted((k, v) for k, v in data.items() if k not in known))
        return cls(run_id, data.get("instance", ""), started, sequence, opened, follows, extra)


def new_run_id() -> str:
    """A fresh run id (a random UUID: unique across machines and restarts)."""
    return str(uuid.uuid4())


def run_tag(log: LogFile) -> RunTag | None:
    """The file's ``rlutf.run`` tag (the last valid one); ``None`` if it has none."""
    found = None
    for name, data in log.metadata():
        if name == RUN_METADATA:
            found = RunTag.from_metadata(data) or found
    return found


@dataclass(frozen=True)
class LogRun:
    """The files of one run, in sequence order.

    Attributes:
        files: the files.
        tags: their ``rlutf.run`` tags (all ``None`` for the run of untagged files).
        start_ns: when the run started (untagged: its earliest ``log_time``), for ordering.
        span: the earliest and latest ``log_time`` of its files' messages (``None``: none, or
            not read).
    """

    files: tuple[Path, ...]
    tags: tuple[RunTag | None, ...]
    start_ns: int | None
    span: tuple[int, int] | None = None

    @property
    def run_id(self) -> str | None:
        """The run's id; ``None`` for files without ``rlutf.run``."""
        first = self.tags[0] if self.tags else None
        return first.run_id if first is not None else None

    @property
    def instance(self) -> str | None:
        """The instance that wrote the run, if the files say."""
        first = self.tags[0] if self.tags else None
        return first.instance if first is not None else None

    @property
    def missing(self) -> list[int]:
        """Sequence numbers absent between 0 and the highest given (files not passed in), but
        for those the recorder took for no file (:attr:`skipped`)."""
        seen = {t.sequence for t in self.tags if t is not None}
        if not seen:
            return []
        skipped = set(self.skipped)
        return [n for n in range(max(seen) + 1) if n not in seen and n not in skipped]

    @property
    def skipped(self) -> list[int]:
        """Sequence numbers a file given says the recorder took for no file (``follows``):
        recording gaps, where it could not write."""
        seen = {t.sequence for t in self.tags if t is not None}
        gaps = {
            n
            for t in self.tags
            if t is not None and t.follows is not None
            for n in range(t.follows + 1, t.sequence)
        }
        return sorted(gaps - seen)

    @property
    def short_label(self) -> str:
        """The label with the run id cut to its first 8 characters (for tables)."""
        if self.run_id is None:
            return "no rlutf.run"
        return f"{self.run_id[:8]} ({self.instance or '?'})"

    @property
    def label(self) -> str:
        """How reports name the run."""
        if self.run_id is None:
            return "files without rlutf.run"
        return f"{self.run_id} ({self.instance or '?'})"


def group_runs(
    paths: Sequence[Path],
    unreadable: list[tuple[Path, LogError]] | None = None,
    rlutf_only: bool = False,
) -> list[LogRun]:
    """Sort files into runs (see the module docstring), ordered by start.

    A file given twice (the same path) counts once.

    Args:
        paths: the files.
        unreadable: if given, files that cannot be read are added to it with their error and
            left out, instead of raising.
        rlutf_only: an MCAP file with none of rlutf's messages (:func:`foreign`: a rosbag2
            recording, another tool's log) cannot be read either, instead of being a run with
            nothing in it (a replay's audit of it passed, having read nothing).

    Raises:
        service.logs.mcapread.LogError: a file is missing, not MCAP, or damaged (unless
            ``unreadable`` is given).
        RunConflict: two different files are the same file number of the same run.
    """
    tagged: dict[str, list[tuple[RunTag, Path]]] = {}
    spans: dict[str | None, list[tuple[int, int]]] = {}  # by run id (None: untagged)
    untagged: list[Path] = []
    seen: set[Path] = set()
    for path in paths:
        key = Path(path).resolve()
        if key in seen:
            continue
        seen.add(key)
        try:
            with LogFile(path) as log:
                tag = run_tag(log)
                span = log.time_range
                why = foreign(log) if rlutf_only else None
            if why is not None:
                raise NotALog(f"{path}: {why}")
        except LogError as err:
            if unreadable is None:
                raise
            unreadable.append((Path(path), err))
            continue
        if tag is None:
            untagged.append(Path(path))
        else:
            tagged.setdefault(tag.run_id, []).append((tag, Path(path)))
        if span is not None:
            spans.setdefault(None if tag is None else tag.run_id, []).append(span)

    def span_of(run_id: str | None) -> tuple[int, int] | None:
        found = spans.get(run_id)
        return (min(a for a, _ in found), max(b for _, b in found)) if found else None

    runs = [_tagged_run(run_id, members, span_of(run_id)) for run_id, members in tagged.items()]
    if untagged:
        span = span_of(None)
        start = span[0] if span is not None else None
        runs.append(LogRun(tuple(untagged), (None,) * len(untagged), start, span))
    return sorted(runs, key=lambda r: (r.start_ns is None, r.start_ns or 0, r.run_id or ""))


def foreign(log: LogFile) -> str | None:
    """Why ``log`` is not an rlutf log (a sentence without the file's name), or ``None``: it
    has channels and none of them carries one of rlutf's schemas (``rlutf.*``). A ROS 2
    recording is named as one, with the ``rlutf replay --ros2`` command that localizes a robot
    in it."""
    channels = log.channels()
    if not channels or any(c.schema_name.startswith("rlutf.") for c in channels):
        return None
    shown = ", ".join(f"{c.topic} ({c.schema_name or 'no schema'})" for c in channels[:4])
    more = f" and {len(channels) - 4} more" if len(channels) > 4 else ""
    if not any(c.message_encoding == "cdr" for c in channels):
        return f"not an rlutf log: none of its channels carries an rlutf message ({shown}{more})"
    bag = log.path.parent if (log.path.parent / "metadata.yaml").is_file() else log.path
    scan = next((c.topic for c in channels if c.schema_name.endswith("/LaserScan")), "TOPIC")
    odom = next((c.topic for c in channels if c.schema_name.endswith("/Odometry")), "TOPIC")
    return (
        f"a ROS 2 recording ({shown}{more}), not an rlutf log: localize a robot "
        f"in it with rlutf replay --ros2 {bag} --map ID --scan-topic {scan} --odom-topic {odom} "
        "[--initial-pose X,Y,THETA]"
    )


def _tagged_run(
    run_id: str, members: Iterable[tuple[RunTag, Path]], span: tuple[int, int] | None
) -> LogRun:
    ordered = sorted(members, key=lambda m: (m[0].sequence, str(m[1])))
    for (a, path_a), (b, path_b) in itertools.pairwise(ordered):
        if a.sequence == b.sequence:
            raise RunConflict(
                f"{path_a} and {path_b} are both file {a.sequence} of run {run_id}: "
                "pass only one of them (a copy, or a recovered file beside its original?)"
            )
    return LogRun(
        tuple(p for _, p in ordered),
        tuple(t for t, _ in ordered),
        min(t.started_ns for t, _ in ordered),
        span,
    )


def recordings(runs: Sequence[LogRun]) -> list[list[LogRun]]:
    """Runs (as :func:`group_runs` gives them) grouped by when their messages were logged: runs
    whose spans overlap (the processes of one ``rlutf serve``, the instances of a fleet,
    recording side by side) are one recording; a run that starts after every earlier one ended
    starts another. In time order; runs with no message are left out."""
    spans = sorted(
        ((run.span, k, run) for k, run in enumerate(runs) if run.span is not None),
        key=lambda s: (s[0][0], s[1]),
    )
    groups: list[list[LogRun]] = []
    end = 0
    for (first, last), _, run in spans:
        if groups and first <= end:
            groups[-1].append(run)
            end = max(end, last)
        else:
            groups.append([run])
            end = last
    return groups


def run_outputs(out: str | Path, runs: Sequence[LogRun]) -> list[Path]:
    """Where ``rlutf replay --out OUT`` writes each run's output.

    * OUT is a folder (it exists as one, or is written with a trailing ``/``): every run is
      written into it as ``{stem of the run's first file}.replay.mcap`` (``-2``, ``-3`` ...
      added when two runs' first files share a stem); the folder is created if missing.
    * Otherwise OUT is a file: the output of a single run; with several runs, run ``k`` (in
      the order of :func:`group_runs`, from 1) goes to OUT with ``-run{k}`` before its suffix
      (``x.mcap``: ``x-run1.mcap``, ``x-run2.mcap`` ...).
    """
    text = str(out)
    path = Path(text)
    if text.endswith(("/", "\\")) or path.is_dir():
        names: list[Path] = []
        for run in runs:
            stem = run.files[0].name.removesuffix(".mcap") if run.files else "run"
            name, n = f"{stem}.replay.mcap", 1
            while path / name in names:
                n += 1
                name = f"{stem}-{n}.replay.mcap"
            names.append(path / name)
        return names
    if len(runs) <= 1:
        return [path]
    suffix = path.suffix or ".mcap"
    stem = path.name.removesuffix(path.suffix)
    return [path.with_name(f"{stem}-run{k}{suffix}") for k in range(1, len(runs) + 1)]


def unfinished_logs(paths: Sequence[Path]) -> list[Path]:
    """The unfinished logs (``*.mcap.part``) in the folders among ``paths``, in name order:
    what :func:`log_files` leaves out of a folder (a log being recorded, or one a crash left).

    A folder whose finished logs are all among ``paths`` counts as given: ``logs/*.mcap`` is
    how the shell gives ``logs/``. Before, ``rlutf replay logs/*.mcap`` (the command the
    operations guide shows) passed with the logs a ``kill -9`` left unread and unnamed, where
    ``rlutf replay logs/`` said ``incomplete``."""
    folders = {Path(path) for path in paths if Path(path).is_dir()}
    given = {Path(path).resolve() for path in paths if not Path(path).is_dir()}
    for parent in {Path(path).parent for path in paths if not Path(path).is_dir()}:
        try:
            logs = {e.resolve() for e in parent.iterdir() if e.name.endswith(".mcap")}
        except OSError:  # a file's folder that cannot be listed: its files are read alone
            continue
        if logs and logs <= given:
            folders.add(parent)
    found = (p for folder in folders for p in folder.iterdir())
    return sorted(p for p in found if p.name.endswith(".mcap.part") and p.is_file())


def _a_log_file(entry: Path, suffix: str) -> None:
    """Refuse a folder's ``*.mcap`` entry that is no file: left out, the logs it should hold
    would go unread, and an audit of the folder pass without them."""
    if entry.is_file():
        return
    what = (
        f"a symbolic link to {entry.readlink()}, which does not exist"
        if entry.is_symlink() and not entry.exists()
        else "a folder"
        if entry.is_dir()
        else not_a_file(entry) or "not a file"
    )
    raise NotALog(
        f"{entry}: {what}; every *{suffix} entry of a log folder is read as a log: put the log "
        "there, or give the other logs as files"
    )


def log_files(paths: Sequence[Path], suffix: str = ".mcap") -> list[Path]:
    """The log files ``paths`` name: a file as it is, a folder as the files in it (not in its
    subfolders) whose names end in ``suffix``, in name order.

    A log folder can then be given as it is (``rlutf replay logs/``), as a shell glob over it
    would give its files; grouping them into runs (:func:`group_runs`) does not depend on
    their order.

    Raises:
        service.logs.mcapread.NotALog: a folder holds no such file (the message says what it
            holds instead: unfinished ``.mcap.part`` logs, and how to read them), or an entry
            of that name that is no file (a dangling link, a folder, a FIFO).
    """
    files: list[Path] = []
    for path in paths:
        if not Path(path).is_dir():
            files.append(Path(path))
            continue
        entries = sorted(p for p in Path(path).iterdir() if p.name.endswith(suffix))
        for entry in entries:
            _a_log_file(entry, suffix)
        found = entries
        if not found:
            parts = [p for p in Path(path).iterdir() if p.name.endswith(".mcap.part")]
            whole = [p for p in Path(path).iterdir() if p.name.endswith(".mcap")]
            hint = ""
            if parts and suffix == ".mcap":
                recording = sum(not left_unfinished(p) for p in parts)
                now = (
                    f", {recording} of them being recorded now (a running service finishes "
                    "each, renamed *.mcap, at rotation, record_max_seconds, or when it stops)"
                    if recording
                    else ""
                )
                hint = (
                    f"; it holds {len(parts)} unfinished log(s) (.mcap.part){now}: copy what "
                    f"they hold with rlutf log recover {path}/ FOLDER, then use FOLDER"
                )
            elif whole and suffix == ".mcap.part":
                hint = (
                    f"; it holds {len(whole)} complete log(s) (.mcap): nothing to recover, read "
                    f"them as they are (rlutf replay {path}/ OUT.mcap, rlutf log info {path}/)"
                )
            if not parts and (Path(path) / "metadata.yaml").is_file():  # a rosbag2 (sqlite3)
                hint = (
                    "; it is a rosbag2 recording (metadata.yaml): rlutf replay --ros2 and "
                    "rlutf map build --ros2 read it"
                )
            raise NotALog(f"{path}: a folder with no log file (*{suffix}) in it{hint}")
        files.extend(found)
    return files
