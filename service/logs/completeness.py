"""Whether a run's files were read whole: what an audit could not read, and what the recorder
said each file held (:func:`check_run`).

An audit that passes says that every recorded pose it read was reproduced; it can say nothing of
the records it did not read, so it must know of them. Four things tell it:

* Messages on channels without a schema (schema id 0, or a schema without a name): readers pick
  channels by schema name (WIRE.md), so what these held cannot be told. ``rlutf log recover``
  writes such channels where the chunk that declared their schema was damaged, and another
  tool's salvage may too. They are read and counted per topic
  (:meth:`~service.logs.mcapread.LogFile.read_counts`).
* ``rlutf.recovered`` (:class:`~service.logs.manifest.Recovered`): what ``rlutf log recover``
  could not copy into a file (damaged chunks, unreadable stretches, messages whose channel was
  lost), which is not in the file to be counted.
* ``rlutf.manifest`` (:class:`~service.logs.manifest.Manifest`), written by the recorder as it
  finishes a file: its messages per topic and schema, held against those read (on the WIRE.md
  channels, the ``rlutf.*`` schemas, that were read), and whether the run's recording ended with
  it, so that the run's later files left out are found. Its absence proves nothing either way:
  a file cut short by a crash was never finished, and logs written before it have none; the
  check is then said not to be possible.
* The run's sequence numbers (``rlutf.run``): a number below the highest given that no file
  given has, unless a file says the recorder skipped it (``follows``: a recording gap).

A run is *incomplete* when records of it were not read (exit 2: "this log could not be read
whole"), *altered* when a file its recorder finished, read whole, does not hold what its
manifest lists (a failed audit, exit 1: "this log was changed after it was recorded"). Missing
files count as incomplete only for runs whose files say how they follow one another (written
with manifests); older logs are audited as before, with a note that the check was not possible.
Nothing here makes an audit pass that would fail without it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from service.logs.manifest import MANIFEST_METADATA, RECOVERED_METADATA, Manifest, Recovered
from service.logs.mcapread import LogFile, robot_topic
from service.logs.runs import LogRun, RunTag, run_tag

#: The schemas a manifest is checked on: the WIRE.md channels (views are written anew by copies).
WIRE_SCHEMAS = "rlutf."
#: At most this many topics are named in one note (the others are counted).
SHOWN = 6


@dataclass(frozen=True)
class FileCheck:
    """What one file of a run held that was not read, and how it compares with its manifest.

    Attributes:
        path: the file.
        sequence: its number within its run (``None``: no ``rlutf.run``).
        unread: ``(topic, messages)`` on channels without a schema, as read.
        recovered: its ``rlutf.recovered`` records (one per salvage it went through).
        manifest: its ``rlutf.manifest`` (``None``: none that names its run and number),
            without the messages it lists (a run of weeks has thousands of files).
        differs: ``(topic, schema, listed, read)`` where the manifest and the file disagree.
    """

    path: Path
    sequence: int | None
    unread: tuple[tuple[str, int], ...] = ()
    recovered: tuple[Recovered, ...] = ()
    manifest: Manifest | None = None
    differs: tuple[tuple[str, str, int, int], ...] = ()

    @property
    def lost_inside(self) -> bool:
        """Whether a salvage of it left messages out from within it (not only after a cut)."""
        return any(r.lost_inside for r in self.recovered)

    @property
    def whole(self) -> bool:
        """Whether every message it holds was read and none was left out within it."""
        return not self.unread and not self.lost_inside

    @property
    def altered(self) -> bool:
        """Whether it differs from its manifest with nothing to explain it: it was read whole
        (a copy salvaged after a cut holds its manifest only if the cut came after it, after
        every message)."""
        return bool(self.differs) and self.whole


def _manifest(metadata: Iterable[tuple[str, dict[str, str]]], tag: RunTag) -> Manifest | None:
    found = None
    for name, data in metadata:
        if name == MANIFEST_METADATA:
            manifest = Manifest.from_metadata(data)
            if manifest is not None and (manifest.run_id, manifest.sequence) == (
                tag.run_id,
                tag.sequence,
            ):
                found = manifest
    return found


def check_file(log: LogFile, tag: RunTag | None) -> FileCheck:
    """The check of a file whose messages were read through (:meth:`LogFile.messages`)."""
    counts, covered = log.read_counts()
    metadata = log.metadata()
    recovered = tuple(Recovered.from_metadata(d) for n, d in metadata if n == RECOVERED_METADATA)
    unread = tuple(sorted((t, n) for (t, s), n in counts.items() if s == "" and n))
    manifest = _manifest(metadata, tag) if tag is not None else None
    differs: list[tuple[str, str, int, int]] = []
    if manifest is not None:

        def checked(schema: str) -> bool:
            return schema.startswith(WIRE_SCHEMAS) and (covered is None or schema in covered)

        listed = {(t, s): n for t, s, n in manifest.messages if checked(s)}
        read = {k: n for k, n in counts.items() if checked(k[1])}
        differs = [
            (*key, listed.get(key, 0), read.get(key, 0))
            for key in sorted(listed.keys() | read.keys())
            if listed.get(key, 0) != read.get(key, 0)
        ]
    sequence = tag.sequence if tag is not None else None
    if manifest is not None:  # what it lists is held against the file: only that is kept
        manifest = replace(manifest, messages=())
    return FileCheck(log.path, sequence, unread, recovered, manifest, tuple(differs))


@dataclass(frozen=True)
class Completeness:
    """A run's files against what they should hold (see the module docstring).

    Attributes:
        files: each file's check, in the run's order.
        missing: the run's file numbers below the highest given that no file given has.
        skipped: the numbers the recorder took for no file (recording gaps).
        checked: the run's files say how they follow one another (a manifest or ``follows``):
            missing files and the run's end can be checked.
    """

    files: tuple[FileCheck, ...] = ()
    missing: tuple[int, ...] = ()
    skipped: tuple[int, ...] = ()
    checked: bool = False

    @property
    def last(self) -> FileCheck | None:
        """The file of the highest number given (``None``: no file with ``rlutf.run``)."""
        tagged = [f for f in self.files if f.sequence is not None]
        return max(tagged, key=lambda f: f.sequence or 0) if tagged else None

    @property
    def followed(self) -> bool:
        """Whether the last file given says the run went on after it."""
        last = self.last
        return last is not None and last.manifest is not None and not last.manifest.last

    @property
    def altered(self) -> tuple[FileCheck, ...]:
        """The files that were changed after they were recorded."""
        return tuple(f for f in self.files if f.altered)

    def _run_wide(self) -> bool:
        """Whether what was not read may concern any robot."""
        unread = (t for f in self.files for t, _ in f.unread)
        return (
            any(f.lost_inside for f in self.files)
            or (self.checked and (bool(self.missing) or self.followed))
            or any(robot_topic(t) is None for t in unread)
        )

    @property
    def incomplete(self) -> bool:
        """Whether records of the run were not read (the audit cannot pass)."""
        return self._run_wide() or any(f.unread for f in self.files)

    def affected(self) -> frozenset[str] | None:
        """The robots whose records were not all read (``None``: any robot may be)."""
        if self._run_wide():
            return None
        found = (robot_topic(t) for f in self.files for t, _ in f.unread)
        return frozenset(w.robot for w in found if w is not None)

    def notes(self, run: bool = True) -> list[tuple[str, str]]:
        """What to tell of the run (of its files alone, without ``run``: its files not given
        and its recording gaps left out), each ``(kind, text)``: ``altered`` (the audit fails),
        ``incomplete`` (it cannot pass) or ``note`` (it stands, qualified)."""
        altered, unread = self.altered, [f for f in self.files if f.unread]
        salvaged = [(f, r) for f in self.files for r in f.recovered if _said(r)]
        out = [("altered", _altered(f)) for f in altered[:SHOWN]]
        if len(altered) > SHOWN:
            more = len(altered) - SHOWN
            out.append(("altered", f"{more} more file(s) do not hold what their manifest lists"))
        out += [("incomplete", _unread(f)) for f in unread[:SHOWN]]
        if len(unread) > SHOWN:
            lost = sum(n for f in unread[SHOWN:] for _, n in f.unread)
            out.append(
                (
                    "incomplete",
                    f"{len(unread) - SHOWN} more file(s) hold {lost} message(s) on channels "
                    "without a schema, not read",
                )
            )
        out += [(_kind(r), _salvaged(f.path, r)) for f, r in salvaged[:SHOWN]]
        if len(salvaged) > SHOWN:
            kind = "incomplete" if any(r.lost_inside for _, r in salvaged[SHOWN:]) else "note"
            more = len(salvaged) - SHOWN
            out.append((kind, f"{more} more file(s) salvaged by rlutf log recover lack records"))
        return out + (self._sequence_notes() if run else []) + self._manifest_notes()

    def _sequence_notes(self) -> list[tuple[str, str]]:
        out = []
        if self.missing:
            text = f"file(s) {_numbers(self.missing)} of the run are not given"
            if self.checked:
                out.append(("incomplete", f"{text}: give every file of the run (its log folder)"))
            else:
                out.append(("note", f"{text}: poses after a missing file may not reproduce"))
        if self.skipped:
            out.append(
                (
                    "note",
                    f"file number(s) {_numbers(self.skipped)} of the run were taken by "
                    "no file: recording gaps (the recorder could not write)",
                )
            )
        last = self.last
        if self.followed and last is not None:
            out.append(
                (
                    "incomplete",
                    f"{last.path.name}, file {last.sequence} of the run, was followed by "
                    "another (its rlutf.manifest says the run went on): give the run's later "
                    "files too",
                )
            )
        return out

    def _manifest_notes(self) -> list[tuple[str, str]]:
        out = []
        reasons = {
            "salvaged": "salvaged by rlutf log recover from a file its recorder never finished",
            "unfinished": "not finished by their recorder: cut short by a crash and recovered",
            "older": "written before rlutf wrote one, or by another tool",
        }
        for why, text in reasons.items():
            bare = [f for f in self.files if f.manifest is None and self._why(f) == why]
            if bare:
                names = ", ".join(f.path.name for f in bare[:SHOWN]) + _more(len(bare))
                out.append(
                    (
                        "note",
                        f"no rlutf.manifest in {names} ({text}): whether a robot's records were "
                        "removed from them, or files of the run after them, cannot be checked",
                    )
                )
        return out

    def _why(self, f: FileCheck) -> str:
        """Why a file has no manifest, as far as can be told."""
        if any(not r.complete for r in f.recovered):
            return "salvaged"
        return "unfinished" if self.checked else "older"


def _numbers(numbers: Sequence[int]) -> str:
    return ", ".join(map(str, numbers[:SHOWN])) + _more(len(numbers))


def _more(n: int) -> str:
    return f" and {n - SHOWN} more" if n > SHOWN else ""


def _altered(f: FileCheck) -> str:
    said = "; ".join(f"{t} ({s}): {a} listed, {b} read" for t, s, a, b in f.differs[:SHOWN])
    robots = sorted({w.robot for t, *_ in f.differs if (w := robot_topic(t)) is not None})
    who = f", for robot(s) {', '.join(robots)}" if robots else ""
    return (
        f"{f.path.name} does not hold what its recorder listed in it when it finished it "
        f"(rlutf.manifest){who}: {said}{_more(len(f.differs))}: the log was changed after it "
        "was recorded"
    )


def _unread(f: FileCheck) -> str:
    total = sum(n for _, n in f.unread)
    said = ", ".join(f"{t} {n}" for t, n in f.unread[:SHOWN]) + _more(len(f.unread))
    return (
        f"{f.path.name}: {total} message(s) on channels without a schema not read ({said}): "
        "readers pick channels by their schema, so what these held cannot be told (a copy "
        "salvaged by rlutf log recover has lost the schemas declared in the chunks it could not "
        "copy): audit an undamaged copy of the log if there is one"
    )


def _said(r: Recovered) -> bool:
    return r.lost_inside or not r.complete


def _kind(r: Recovered) -> str:
    return "incomplete" if r.lost_inside else "note"


def _salvaged(path: Path, r: Recovered) -> str:
    source = f"from {r.source} " if r.source else ""
    if not r.lost_inside:
        cut = f" at byte {r.cut_at:,}" if r.cut_at is not None else ""
        return (
            f"{path.name} was salvaged {source}by rlutf log recover from a file cut short{cut}: "
            "what came after the cut is not in it (the poses of the log's last 30 s are "
            "unverified, as after any crash)"
        )
    return (
        f"{path.name} was salvaged {source}by rlutf log recover, which could not copy "
        f"{r.bad_chunks} damaged chunk(s), {r.unreadable} unreadable stretch(es) and "
        f"{r.lost_messages} message(s) whose channel record was lost: what they held is not in "
        "it; audit an undamaged copy of the log if there is one"
    )


def completeness(files: Sequence[FileCheck], tags: Sequence[RunTag | None]) -> Completeness:
    """The check of one run from its files' checks and ``rlutf.run`` tags."""
    run = LogRun(tuple(f.path for f in files), tuple(tags), None)
    checked = any(f.manifest is not None for f in files) or any(
        t is not None and t.follows is not None for t in tags
    )
    return Completeness(tuple(files), tuple(run.missing), tuple(run.skipped), checked)


def check_run(logs: Sequence[LogFile]) -> Completeness:
    """The check of one run's files, once their messages were read through."""
    tags = [run_tag(log) for log in logs]
    return completeness([check_file(log, tag) for log, tag in zip(logs, tags, strict=True)], tags)
