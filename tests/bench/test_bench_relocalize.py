"""Issue 13's benchmark: the ambiguity oracle, the grading, the targets and the sampler."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.kidnap import KidnapRun, kidnap_path
from bench.reloccases import (
    TWIN_TRUTH,
    Oracle,
    RelocProfile,
    building,
    close,
    oracle,
    sample_queries,
    twin_rooms,
)
from bench.relocgrade import Case, Precompute, Summary, summarise
from bench.reloctables import reloc_targets
from rlutf.motion import relative
from rlutf.relocalize import Hypothesis, Relocalization, relocalize
from rlutf.sim import LidarModel, make_building, random_free_point, simulate_scan


def _rows(rows: list[str]) -> dict[str, str]:
    """Target rows by their first cell, to their last cell (met or not)."""
    out = {}
    for r in rows[2:]:
        cells = [c.strip() for c in r.strip("|").split("|")]
        out[cells[0]] = cells[-1]
    return out


def test_oracle_calls_identical_rooms_ambiguous() -> None:
    world = twin_rooms()
    scan = simulate_scan(world, TWIN_TRUTH, LidarModel(), np.random.default_rng(4))
    twin = TWIN_TRUTH + np.array([10.0, 0.0, 0.0])
    found = oracle(world, scan, TWIN_TRUTH, [twin])
    assert found.ambiguous
    assert found.rival is not None and close(found.rival, twin, 0.05, 1.0)
    # the method's own hypotheses do as well as the hand-made twin
    result = relocalize(world, scan)
    assert oracle(world, scan, TWIN_TRUTH, [h.pose for h in result.hypotheses]).ambiguous
    # a candidate at the truth itself is no rival
    assert not oracle(world, scan, TWIN_TRUTH, [TWIN_TRUTH.copy()]).ambiguous


def test_oracle_calls_a_random_building_pose_not_ambiguous() -> None:
    rng = np.random.default_rng(7)
    world = make_building(rng, 24.0, 14.0, 3, 2)
    p = random_free_point(world, rng, 0.3)
    truth = np.array([p[0], p[1], 0.7])
    scan = simulate_scan(world, truth, LidarModel(), rng)
    result = relocalize(world, scan)
    found = oracle(world, scan, truth, [h.pose for h in result.hypotheses])
    assert not found.ambiguous
    assert found.truth_fit > 0.95
    assert found.rival_fit < found.truth_fit - 0.05


def test_query_sampler_is_seeded_and_stays_in_free_space() -> None:
    world = building("building-300")
    a = sample_queries(world, np.random.default_rng(3), 25)
    b = sample_queries(world, np.random.default_rng(3), 25)
    c = sample_queries(world, np.random.default_rng(4), 25)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert world.contains(a[:, :2]).all()
    inner = world.geometry.buffer(-0.29)
    assert all(inner.contains_properly(_pt(x, y)) for x, y in a[:, :2])
    assert np.all(np.abs(a[:, 2]) <= math.pi)


def _pt(x: float, y: float):  # type: ignore[no-untyped-def]
    from shapely.geometry import Point

    return Point(x, y)


def _case(truth: np.ndarray, best: np.ndarray, found: bool, ambiguous: bool, amb: bool) -> Case:
    result = Relocalization((Hypothesis(best, 0.9, 1.0),), found, ambiguous, 0, ())
    return Case(
        "m",
        "default",
        truth,
        None,
        result,
        0.1,
        0.1,
        Oracle(amb, 1.0, 0.0, None),  # type: ignore[arg-type]
    )


def test_grading_counts_confident_wrong_and_ignores_ambiguous_cases_for_success() -> None:
    t = np.zeros(3)
    cases = [
        _case(t, np.array([0.01, 0.0, 0.0]), True, False, False),  # refined right
        _case(t, np.array([0.2, 0.0, 0.0]), True, False, False),  # coarse right only
        _case(t, np.array([3.0, 0.0, 0.0]), True, False, False),  # confident and wrong
        _case(t, np.array([0.0, 0.0, 0.0]), True, True, False),  # said ambiguous: not right
        _case(t, np.array([5.0, 0.0, 0.0]), True, True, True),  # ambiguous, truth not listed
    ]
    s = summarise(cases)
    assert (s.cases, s.ambiguous, s.clear) == (5, 1, 4)
    assert (s.coarse, s.refined, s.wrong, s.listed, s.flagged) == (2, 1, 1, 0, 2)


def _summary(
    name: str, coarse: int, refined: int, wrong: int, p95: float, listed: int = 10
) -> Summary:
    return Summary(
        name, "default", 100, 10, coarse, refined, wrong, listed, 10, 0, 0.1, p95, p95, 0.1
    )


def _kidnap(recovered: int | None, wrong: int) -> KidnapRun:
    z = np.zeros(3)
    return KidnapRun(1, 300.0, 1, z, z, ("start", "lost", "corrected"), z > 0, recovered, wrong,
                     0.0, 0.0)  # fmt: skip


def test_target_rows_say_no_for_a_failing_summary() -> None:
    pre = [Precompute("building-10000", 9700.0, 10, 10, 1.0, 1.0, 1e-5)]
    good = [_summary("building-1000", 90, 90, 0, 0.3), _summary("building-10000", 90, 90, 0, 1.5)]
    ok = _rows(reloc_targets(good, pre, [_kidnap(8, 0)]))
    assert set(ok.values()) == {"yes"}, ok
    bad = [
        _summary("building-1000", 80, 70, 5, 0.9, listed=5),
        _summary("building-10000", 90, 90, 0, 3.0, listed=9),
    ]
    no = _rows(reloc_targets(bad, pre, [_kidnap(None, 2)]))
    assert all(v == "no" for k, v in no.items() if not k.startswith("precomputation")), no
    assert len([v for v in no.values() if v == "no"]) == 8
    assert set(_rows(reloc_targets([], [], [])).values()) == {"no"}


def test_kidnap_path_teleports_while_odometry_sees_no_jump() -> None:
    world = make_building(np.random.default_rng(1), 24.0, 14.0, 3, 2)
    truth, odometry = kidnap_path(world, 1, 30, 10)
    jump = relative(truth[9], truth[10])
    seen = relative(odometry[9], odometry[10])
    assert math.hypot(*jump[:2]) > 0.3 or abs(jump[2]) > 0.2
    assert math.hypot(*seen[:2]) < 0.2
    assert world.contains(truth[:, :2]).all()


def test_only_relocalize_writes_its_own_section(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import bench.__main__ as cli

    tiny = RelocProfile("quick", 2, ("tb3-sandbox",), (1,), 20, 8)
    monkeypatch.setattr(cli, "RELOC_QUICK", tiny)
    out = tmp_path / "B.md"
    out.write_text("# Benchmarks\n\n<!-- begin priors -->\nkept\n<!-- end priors -->\n")
    plots = tmp_path / "plots"
    argv = ["--quick", "--only", "relocalize", "--output", str(out), "--plots", str(plots)]
    assert cli.main(argv) == 0
    text = out.read_text()
    assert "kept" in text
    begin, end = text.index("<!-- begin relocalize -->"), text.index("<!-- end relocalize -->")
    body = text[begin:end]
    assert "| target | result | met |" in body and "tb3-sandbox" in body
    assert (plots / "relocalize-hypotheses.png").exists()
    assert (plots / "relocalize-kidnap.png").exists()
