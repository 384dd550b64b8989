"""``python -m bench.evidence``: a fleet's map health evidence per second, raw and as put."""

from __future__ import annotations

import argparse

from bench.evidence import measure, render


def test_the_evidence_of_a_small_fleet_is_measured_and_compressed() -> None:
    rows = measure(robots=3, seconds=2)
    assert len(rows) == 2
    for cells, raw, put, encode_ms, decode_ms in rows:
        assert cells > 100 and raw > 60 * cells  # 68 bytes a cell, and the header
        assert 0 < put < raw / 3
        assert encode_ms > 0 and decode_ms > 0
    text = render(argparse.Namespace(robots=3, seconds=2))
    assert "python -m bench.evidence --robots 3 --seconds 2 --write" in text
    assert text.splitlines()[-1].startswith("| 3 | ")
