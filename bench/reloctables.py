"""The tables of the relocalization benchmark (:mod:`bench.relocalize`), from its summaries."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from bench.kidnap import KidnapRun
from bench.reloccases import (
    AMBIGUOUS_TARGET,
    COARSE,
    COARSE_TARGET,
    KIDNAP_SCANS,
    REFINED,
    REFINED_TARGET,
    TIME_TARGETS,
    WRONG_TARGET,
)
from bench.relocgrade import Precompute, Summary


def _pct(k: int, n: int) -> str:
    return "-" if n == 0 else f"{100.0 * k / n:.0f} % ({k}/{n})"


def _s(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.3f}"


def results_table(summaries: Sequence[Summary], areas: dict[str, float]) -> list[str]:
    """One row per map, the default settings."""
    rows = [
        "| map | free area m2 | cases | ambiguous (oracle) | coarse right (non-amb.) | "
        "refined right (non-amb.) | confident wrong (all) | truth listed (amb.) | "
        "flagged ambiguous | not found | CPU s median / p95 / max | wall s median |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    rows += [
        f"| {s.map} | {areas[s.map]:.0f} | {s.cases} | {s.ambiguous} | "
        f"{_pct(s.coarse, s.clear)} | {_pct(s.refined, s.clear)} | "
        f"{_pct(s.wrong, s.cases)} | {_pct(s.listed, s.ambiguous)} | {s.flagged} | "
        f"{s.not_found} | {_s(s.cpu_median)} / {_s(s.cpu_p95)} / {_s(s.cpu_max)} | "
        f"{_s(s.wall_median)} |"
        for s in summaries
    ]
    return rows


def pooled(summaries: Sequence[Summary]) -> Summary:
    """The maps' counts added up (times: the largest p95 and max, median of medians)."""
    if not summaries:
        return Summary("", "", 0, 0, 0, 0, 0, 0, 0, 0, *([math.nan] * 4))
    return Summary(
        "all",
        summaries[0].setting,
        sum(s.cases for s in summaries),
        sum(s.ambiguous for s in summaries),
        sum(s.coarse for s in summaries),
        sum(s.refined for s in summaries),
        sum(s.wrong for s in summaries),
        sum(s.listed for s in summaries),
        sum(s.flagged for s in summaries),
        sum(s.not_found for s in summaries),
        float(np.median([s.cpu_median for s in summaries])),
        max(s.cpu_p95 for s in summaries),
        max(s.cpu_max for s in summaries),
        float(np.median([s.wall_median for s in summaries])),
    )


def turning_table(default: Sequence[Summary], turning: Sequence[Summary]) -> list[str]:
    """Default against ``turning_rank=True``, map by map."""
    rows = [
        "| map | coarse right: default / turning | refined right | flagged ambiguous | "
        "confident wrong | truth listed (amb.) | CPU p95 s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for d, t in [*zip(default, turning, strict=True), (pooled(default), pooled(turning))]:
        rows.append(
            f"| {d.map} | {_pct(d.coarse, d.clear)} / {_pct(t.coarse, t.clear)} | "
            f"{_pct(d.refined, d.clear)} / {_pct(t.refined, t.clear)} | "
            f"{d.flagged} / {t.flagged} | {d.wrong} / {t.wrong} | "
            f"{_pct(d.listed, d.ambiguous)} / {_pct(t.listed, t.ambiguous)} | "
            f"{_s(d.cpu_p95)} / {_s(t.cpu_p95)} |"
        )
    return rows


def _n(n: int, more: str, noun: str) -> str:
    return f"{n} {more} {noun}{'' if n == 1 else 's'}"


def turning_bought(default: Sequence[Summary], turning: Sequence[Summary]) -> str:
    """One sentence, from the numbers, on what ``turning_rank`` changed."""
    d, t = pooled(default), pooled(turning)
    if d.cases == 0:
        return "What the turning function bought: not measured."
    dt = [b.cpu_median / a.cpu_median - 1.0 for a, b in zip(default, turning, strict=True)]
    parts = [
        f"ambiguous answers {d.flagged} -> {t.flagged} of {d.cases}",
        f"coarse right {d.coarse} -> {t.coarse} of {d.clear} non-ambiguous",
        f"refined right {d.refined} -> {t.refined}",
        f"confident wrong {d.wrong} -> {t.wrong}",
        f"truth listed in ambiguous cases {d.listed} -> {t.listed} of {d.ambiguous}",
        f"median CPU time per call {100.0 * float(np.median(dt)):+.0f} % (median over maps)",
    ]
    more = t.coarse - d.coarse
    decided = (
        _n(more, "more", "non-ambiguous case") + " decided right"
        if more > 0
        else (
            _n(-more, "fewer", "case") + " decided right" if more < 0 else "no more decided right"
        )
    )
    if t.wrong > d.wrong:
        verdict = (
            f"{_n(t.wrong - d.wrong, 'more', 'confident-wrong answer')} and {decided}: not worth "
            "turning on by default"
        )
    elif t.wrong < d.wrong:
        verdict = f"{_n(d.wrong - t.wrong, 'fewer', 'confident-wrong answer')} and {decided}"
    elif more > 0:
        verdict = f"{decided}, with no more confident-wrong answers"
    elif more < 0:
        verdict = f"{decided}, no fewer confident-wrong answers: it does not help"
    else:
        verdict = "nothing measurable on these cases"
    return "What the turning function bought (`turning_rank=True` vs default, all maps): " + (
        "; ".join(parts) + f". In short: {verdict}."
    )


def precompute_table(pre: Sequence[Precompute]) -> list[str]:
    """The search grid per map."""
    rows = [
        "| map | free area m2 | grid cells (6 levels) | memory MB | first call CPU s | "
        "wall s | cached call ms |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    rows += [
        f"| {p.map} | {p.area:.0f} | {p.cells:,} | {p.nbytes / 1e6:.1f} | {p.cpu:.3f} | "
        f"{p.wall:.3f} | {1e3 * p.cached:.3f} |"
        for p in pre
    ]
    return rows


def kidnap_table(runs: Sequence[KidnapRun]) -> list[str]:
    """One row per kidnapped run."""
    rows = [
        "| seed | building m2 | kidnap at scan | back within 5 cm / 1 deg after (scans) | "
        "confident wrong poses in between | worst of them m | relocalizing updates | "
        "their CPU s |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in runs:
        back = "never" if r.recovered is None else str(r.recovered)
        rows.append(
            f"| {r.seed} | {r.area:.0f} | {r.at} | {back} | {r.wrong} | "
            f"{r.worst_wrong:.2f} | {int(r.relocalizing.sum())} | {r.relocalize_cpu:.2f} |"
        )
    return rows


def _yes(ok: bool) -> str:
    return "yes" if ok else "no"


def reloc_targets(
    default: Sequence[Summary],
    precomputes: Sequence[Precompute],
    kidnaps: Sequence[KidnapRun],
) -> list[str]:
    """The issue's targets, measured (default settings) and met or not."""
    rows = ["| target | result | met |", "| --- | --- | --- |"]
    p = pooled(default)

    def row(target: str, result: str, ok: bool) -> None:
        rows.append(f"| {target} | {result} | {_yes(ok)} |")

    def per_map(attr: str, of: str) -> str:
        return "; ".join(f"{s.map} {_pct(getattr(s, attr), getattr(s, of))}" for s in default)

    row(
        f"first answer `corrected` within {COARSE[0]:g} m / {COARSE[1]:g} deg in >= "
        f"{100 * COARSE_TARGET:.0f} % of non-ambiguous cases",
        f"all {_pct(p.coarse, p.clear)}: {per_map('coarse', 'clear')}",
        p.clear > 0 and p.coarse >= COARSE_TARGET * p.clear,
    )
    row(
        f"... within {100 * REFINED[0]:g} cm / {REFINED[1]:g} deg after refinement in >= "
        f"{100 * REFINED_TARGET:.0f} %",
        f"all {_pct(p.refined, p.clear)}: {per_map('refined', 'clear')}",
        p.clear > 0 and p.refined >= REFINED_TARGET * p.clear,
    )
    row(
        f"confident (`corrected`) and wrong in <= {100 * WRONG_TARGET:g} % of all cases",
        f"all {_pct(p.wrong, p.cases)}: {per_map('wrong', 'cases')}",
        p.cases > 0 and p.wrong <= WRONG_TARGET * p.cases,
    )
    row(
        f"ambiguous cases: truth among the hypotheses >= {100 * AMBIGUOUS_TARGET:.0f} %",
        f"all {_pct(p.listed, p.ambiguous)}"
        + (f": {per_map('listed', 'ambiguous')}" if p.ambiguous else " (no ambiguous case)"),
        p.cases > 0 and (p.ambiguous == 0 or p.listed >= AMBIGUOUS_TARGET * p.ambiguous),
    )
    for name, area, limit in TIME_TARGETS:
        s = next((s for s in default if s.map == name), None)
        row(
            f"time per relocalization p95 <= {limit:g} s on a {area:,.0f} m2 map, one core",
            "not measured" if s is None else f"{name}: p95 {s.cpu_p95:.3f} s CPU",
            s is not None and s.cpu_p95 <= limit,
        )
    big = [q for q in precomputes if q.area <= 10_500]
    row(
        "precomputation once per map version, cached; time and memory reported up to 10,000 m2",
        "; ".join(f"{q.map} {q.cpu:.2f} s, {q.nbytes / 1e6:.1f} MB" for q in big) or "not measured",
        any(q.area >= 9000 for q in big) and all(q.cached < 0.01 for q in big),
    )
    backs = [r.recovered for r in kidnaps]
    row(
        f"kidnapped: back within 5 cm in <= {KIDNAP_SCANS} scans, every run",
        ", ".join("never" if b is None else str(b) for b in backs) or "not measured",
        bool(kidnaps) and all(b is not None and b <= KIDNAP_SCANS for b in backs),
    )
    row(
        "kidnapped: no confident wrong pose published in between",
        ", ".join(str(r.wrong) for r in kidnaps) or "not measured",
        bool(kidnaps) and all(r.wrong == 0 for r in kidnaps),
    )
    return rows
