"""What ``rlutf log info`` and ``replay`` say of a ``.mcap.part`` file
(``service.logs.partfile.part_message``).

Before, a file its recorder left unfinished (a crash, ``kill -9``) was said to have no index
"until the service finishes it" and to be "the file being recorded", as a file being recorded
now: no service will ever finish it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from service.logs.partfile import RECENT_S, part_message


def test_a_file_left_unfinished_is_not_said_to_be_recorded(tmp_path: Path) -> None:
    part = tmp_path / "rlutf-a-20260101T000000Z-001.mcap.part"
    part.write_bytes(b"\x89MCAP0\r\n")
    old = time.time() - RECENT_S - 5
    os.utime(part, (old, old))
    text = part_message(part)
    assert "was left unfinished" in text
    assert "being recorded" not in text
    assert "until the service finishes it" not in text
    assert f"rlutf log recover {part} COPY.mcap" in text


def test_a_file_being_recorded_is_said_to_be(tmp_path: Path) -> None:
    part = tmp_path / "rlutf-a-20260101T000000Z-001.mcap.part"
    part.write_bytes(b"\x89MCAP0\r\n")
    text = part_message(part)
    assert "is being recorded now" in text
    assert "until the service finishes it" in text
