"""An MCAP chunk decompressed within a bound, whatever it declares.

The ``mcap`` library decompresses a chunk whole, to the size its zstd or lz4 frame declares (a
zstd frame's own content size wins over the chunk's ``uncompressed_size``; lz4 looks at
neither): a 33 KB file whose one chunk holds a gigabyte of spaces took 2.1 GB to ``rlutf log
info``, and zstd's ratio lets a 1 MB file ask for 30 GB. A log the service writes has chunks of
about a megabyte (``chunk_size``; one larger message, a map of at most ``max_map_bytes``, makes
one larger), so :data:`MAX_CHUNK_BYTES` refuses none of them. :func:`inflated_size` counts what a
chunk decompresses to, a piece at a time, and stops past the bound; :func:`unpack_chunk` is
``breakup_chunk`` after that check.
"""

from __future__ import annotations

import io
from typing import Final

import lz4.frame  # type: ignore[import-untyped]
import zstandard
from mcap.records import Chunk, McapRecord
from mcap.stream_reader import breakup_chunk

#: Largest chunk read, bytes once decompressed.
MAX_CHUNK_BYTES: Final = 512 * 1024 * 1024
_PIECE: Final = 1 << 18


class ChunkTooLarge(ValueError):
    """A chunk that decompresses (or says it does) to more than the bound."""

    def __init__(self, size: int, limit: int, declared: bool) -> None:
        said = "declares" if declared else "decompresses to"
        super().__init__(
            f"a chunk {said} {size:,} bytes or more, past the {limit:,} bytes rlutf reads "
            "in one chunk (a log the service writes has chunks of about a megabyte)"
        )


def _declared(size: int, limit: int) -> None:
    if size > limit:
        raise ChunkTooLarge(size, limit, declared=True)


def inflated_size(chunk: Chunk, limit: int = MAX_CHUNK_BYTES) -> int:
    """The size ``chunk`` decompresses to: counted a piece at a time, or, for a zstd frame that
    declares its size, that size.

    Raises:
        ChunkTooLarge: it declares, or decompresses to, more than ``limit`` bytes.
        Exception: whatever the decompressor raises on a corrupt frame (as ``breakup_chunk``).
    """
    _declared(chunk.uncompressed_size, limit)
    total = 0
    if chunk.compression == "":
        total = len(chunk.data)
    elif chunk.compression == "zstd":
        size = zstandard.frame_content_size(chunk.data)  # -1: the frame does not say
        _declared(size, limit)  # allocated up front
        if size >= 0:
            # The library decompresses the first frame to the size its header says (zstd refuses
            # a frame that outgrows it), as every chunk the service writes says it: bounded
            # without decompressing it here too.
            return int(size)
        reader = zstandard.ZstdDecompressor().stream_reader(
            io.BytesIO(chunk.data), read_across_frames=True
        )
        while piece := reader.read(_PIECE):
            total += len(piece)
            if total > limit:
                break
    elif chunk.compression == "lz4":
        _declared(int(lz4.frame.get_frame_info(chunk.data).get("content_size", 0)), limit)
        lz4d = lz4.frame.LZ4FrameDecompressor()
        total = len(lz4d.decompress(chunk.data, max_length=_PIECE))
        while total <= limit and not lz4d.eof and not lz4d.needs_input:
            total += len(lz4d.decompress(b"", max_length=_PIECE))
    else:
        return chunk.uncompressed_size  # the library refuses an unknown compression itself
    if total > limit:
        raise ChunkTooLarge(total, limit, declared=False)
    return total


def unpack_chunk(chunk: Chunk, limit: int = MAX_CHUNK_BYTES) -> list[McapRecord]:
    """The records of a chunk (``breakup_chunk`` with its CRC checked), after
    :func:`inflated_size` has bounded it.

    Raises:
        ChunkTooLarge: as :func:`inflated_size`.
        Exception: a bad CRC or a corrupt frame (as ``breakup_chunk``).
    """
    inflated_size(chunk, limit)
    return breakup_chunk(chunk, validate_crc=True)
