"""Two metadata records that tell an audit what a file held beyond what it can read of it.

* ``rlutf.manifest`` (:class:`Manifest`): written by the recorder (and by ``rlutf replay`` into
  its output) as it finishes a file, after the file's last message: the file's run and sequence
  number, its messages per topic and schema, and whether the run's recording ended with it
  (``last``: the recorder stopped; ``false``: it rotated to a next file). A robot's records
  removed from a finished file, or the run's later files left out, are found by holding this
  record against the messages read (:mod:`service.logs.completeness`). A file cut short by a
  crash has none: it was never finished.
* ``rlutf.recovered`` (:class:`Recovered`): written by ``rlutf log recover`` into each file it
  salvages: what it could not copy (damaged chunks, unreadable stretches, messages whose channel
  record was lost) and whether the input was cut short. Those messages are not in the copy, so
  no reader of it can count them otherwise.

MCAP metadata values are strings: numbers are written in decimal, booleans as ``true`` or
``false``, the manifest's messages as JSON text ``[[topic, schema, count], ...]``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

MANIFEST_METADATA = "rlutf.manifest"
"""Name of the metadata record the recorder writes as it finishes a file."""
RECOVERED_METADATA = "rlutf.recovered"
"""Name of the metadata record ``rlutf log recover`` writes into what it salvages."""


class _Counted(Protocol):
    def counts(self) -> Mapping[tuple[str, str], int]: ...


def _flag(text: str | None) -> bool | None:
    return {"true": True, "false": False}.get(text or "")


def _number(text: str | None) -> int | None:
    try:
        value = int(text or "")
    except ValueError:
        return None
    return value if value >= 0 else None


@dataclass(frozen=True)
class Manifest:
    """A file's ``rlutf.manifest`` record.

    Attributes:
        run_id: the run (as its ``rlutf.run`` record).
        sequence: the file's number within the run.
        last: the run's recording ended with this file (no file of the run follows it).
        messages: ``(topic, schema name, messages)`` for every channel of the file, sorted.
    """

    run_id: str
    sequence: int
    last: bool
    messages: tuple[tuple[str, str, int], ...]

    @classmethod
    def of(cls, writer: _Counted, run_id: str, sequence: int, last: bool) -> Manifest:
        """The manifest of what ``writer`` wrote (its messages per topic and schema)."""
        counts = sorted((t, s, n) for (t, s), n in writer.counts().items() if n)
        return cls(run_id, sequence, last, tuple(counts))

    def to_metadata(self) -> dict[str, str]:
        """The record's data."""
        return {
            "run_id": self.run_id,
            "sequence": str(self.sequence),
            "last": "true" if self.last else "false",
            "messages": json.dumps([list(m) for m in self.messages], separators=(",", ":")),
        }

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> Manifest | None:
        """The manifest in a record's data; ``None`` if a field is missing or malformed."""
        sequence, last = _number(data.get("sequence")), _flag(data.get("last"))
        try:
            listed: Any = json.loads(data.get("messages", ""))
        except (ValueError, RecursionError):
            return None
        if not data.get("run_id") or sequence is None or last is None:
            return None
        if not isinstance(listed, list):
            return None
        messages = []
        for item in listed:
            if not (isinstance(item, list) and len(item) == 3):
                return None
            topic, schema, count = item
            valid = isinstance(topic, str) and isinstance(schema, str)
            if not valid or type(count) is not int or count < 0:
                return None
            messages.append((topic, schema, count))
        return cls(data["run_id"], sequence, last, tuple(sorted(messages)))


@dataclass(frozen=True)
class Recovered:
    """A file's ``rlutf.recovered`` record: what ``rlutf log recover`` could not copy into it.

    Attributes:
        source: the name of the file it was recovered from.
        complete: the input was read to its footer (not cut short).
        cut_at: where the input was cut short (the byte its last readable record ends at).
        bad_chunks: chunks skipped as damaged (their messages are not in the file).
        unreadable: unreadable stretches passed over to the next readable record.
        lost_messages: messages left out because the record of their channel was lost.
    """

    source: str
    complete: bool
    cut_at: int | None
    bad_chunks: int
    unreadable: int
    lost_messages: int

    @property
    def lost_inside(self) -> bool:
        """Whether messages are missing from within the file, not only after a cut."""
        return bool(self.bad_chunks or self.unreadable or self.lost_messages)

    def to_metadata(self) -> dict[str, str]:
        """The record's data."""
        return {
            "source": self.source,
            "complete": "true" if self.complete else "false",
            "cut_at": "" if self.cut_at is None else str(self.cut_at),
            "bad_chunks": str(self.bad_chunks),
            "unreadable": str(self.unreadable),
            "lost_messages": str(self.lost_messages),
        }

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> Recovered:
        """The record in its data. A field that is missing or malformed counts as a loss: the
        record says the file is a salvaged copy, and a copy that cannot say what it lost may
        have lost anything."""
        counts = [_number(data.get(k)) for k in ("bad_chunks", "unreadable", "lost_messages")]
        bad, unreadable, lost = (1 if n is None else n for n in counts)
        return cls(
            data.get("source", ""),
            _flag(data.get("complete")) is True,
            _number(data.get("cut_at")),
            bad,
            unreadable,
            lost,
        )
