"""A log's Foxglove views, written from the log: ``rlutf log views``.

The live service records the WIRE.md channels only (unless ``record_views`` is set): the views
(:mod:`service.logs.foxglove`) cost its main process more than the rest of recording, and they
are optional channels (WIRE.md, MCAP logs). :func:`write_views` makes a copy of a log with them:
every message of the log in ``log_time`` order with its views beside it (same ``log_time``, as
the recorder writes them), every metadata record (``rlutf.config``, ``rlutf.run`` ...) and the
log's own schema documents. The copy belongs to the same run as its source (same ``rlutf.run``),
so ``rlutf replay`` audits it as it would the source; views already in the source are written
anew, not twice.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

from service.logs.foxglove import SCHEMA_NAMES, FoxgloveConverter
from service.logs.mcapfile import DEFAULT_CHUNK_SIZE, MESSAGE_ENCODING, LogWriter
from service.logs.mcapread import LogError, LogFile, NotALog


class ViewsReport(NamedTuple):
    """What :func:`write_views` wrote."""

    messages: int  # copied from the source
    views: int  # Foxglove messages made of them
    metadata: int  # metadata records copied
    replaced: int  # views found in the source, left out (written anew)


def write_views(src: Path, out: Path, chunk_size: int = DEFAULT_CHUNK_SIZE) -> ViewsReport:
    """Copy the log ``src`` to ``out`` with the Foxglove views (see the module docstring).

    ``out`` is written as ``out.part`` and renamed when complete.

    Raises:
        NotALog: ``src`` is missing or not MCAP, or ``out`` is ``src``.
        service.logs.mcapread.DamagedLog: ``src`` is cut short or damaged (recover it first).
        LogError: ``src`` has a channel whose messages are not JSON.
        OSError: ``out`` cannot be written.
    """
    if out.exists() and out.resolve() == src.resolve():
        raise NotALog(f"{out}: the output must not be the input")
    views_in = set(SCHEMA_NAMES)
    with LogFile(src) as lf:
        foreign = [c.topic for c in lf.channels() if c.message_encoding != MESSAGE_ENCODING]
        if foreign:
            raise LogError(
                f"{src}: channel {foreign[0]} is not JSON: views are made of logs in the "
                "WIRE.md layout (for a ROS 2 bag, rlutf replay --ros2 writes them)"
            )
        metadata = lf.metadata()
        schemas = {k: v for k, v in lf.schemas().items() if k not in views_in}
        part = out.with_name(out.name + ".part")
        copied = replaced = 0
        try:
            with open(part, "wb") as stream:
                writer = LogWriter(stream, FoxgloveConverter(), chunk_size, schemas=schemas)
                for name, data in metadata:
                    writer.write_metadata(name, data)
                for record in lf.messages():
                    if record.schema_name in views_in:
                        replaced += 1
                        continue
                    writer.write(record)
                    copied += 1
                total = writer.messages
                writer.finish()
                stream.flush()
                os.fsync(stream.fileno())
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    os.replace(part, out)
    return ViewsReport(copied, total - copied, len(metadata), replaced)
