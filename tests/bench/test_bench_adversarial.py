"""bench.adversarial --quick: the campaign's smoke run (real service, robots and attacker).

The issue's targets are not asserted here (several fail until issue 19 is done, and the machine
is shared); the run must complete, measure every figure and keep the reference run healthy.
"""

from __future__ import annotations

import pytest

from bench import adversarial
from bench.attacks import CLASSES
from bench.goodrobots import score


def test_score_reads_answered_share_gap_and_error() -> None:
    truth = {"g0": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]]}
    start = 100.0
    sent = [("g0", k, k, start + 2.0 + k) for k in (1, 2, 3)]
    poses = [
        ("g0", 1, start + 3.1, 1.05, 0.0, "tracking"),
        ("g0", 3, start + 5.1, 3.0, 0.9, "lost"),  # lost: its error is not counted
        ("g0", 99, start + 5.2, 9.0, 9.0, "tracking"),  # not ours (forged)
    ]
    result = {"sent": sent, "poses": poses, "truth": truth, "start": start, "end": start + 6.0}
    got = score(result, attack_start=start + 3.0)
    assert got["answered"] == pytest.approx(2 / 3)
    assert got["error"] == pytest.approx(0.05)
    assert got["gap"] == pytest.approx(2.0)  # from the pose at 3.1 to the one at 5.1


def test_misses_names_the_targets_missed() -> None:
    good = {
        "class": "scan-1e5",
        "notes": [],
        "health_missed": 0,
        "health_max": 0.2,
        "answered": 0.99,
        "gap": 0.3,
        "error": 0.01,
        "rss_peak": 500.0,
        "term_s": 1.0,
    }
    assert adversarial.misses(good, None) == []
    bad = {**good, "gap": 5.0, "term_s": None, "health_missed": 3}
    assert adversarial.misses(bad, None) == ["health", "gap", "sigterm"]
    flood = {**good, "class": "map-flood", "sent": 9, "last_loaded": 8, "stored": 8}
    assert adversarial.misses(flood, None) == []
    assert adversarial.misses({**flood, "last_loaded": 7}, None) == ["map"]


@pytest.mark.integration
def test_quick_campaign_runs_and_measures(capsys: pytest.CaptureFixture[str]) -> None:
    assert adversarial.QUICK_CLASSES == ["none", "mixed"] and set(CLASSES) >= {"none", "mixed"}
    assert adversarial.main(["--quick", "--duration", "5", "--mixed-duration", "5"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| none |")]
    assert rows, out
    cells = [c.strip() for c in rows[-1].strip("|").split("|")]
    assert cells[-1] == "none", f"the reference run must meet every target: {rows[-1]}"
    mixed = [line for line in out.splitlines() if line.startswith("| mixed |")]
    assert mixed and "bench" not in mixed[-1].split("|")[-2], mixed
