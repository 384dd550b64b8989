"""Markdown of the accuracy and speed sections of ``BENCHMARKS.md``, and the issue's targets.

Targets (issue 6), checked on the default localizer (``LocalizerConfig()``):

1. translation RMSE at most twice the Cramer-Rao bound on the nominal scenario;
2. no divergence (an update over 0.5 m off) in any scenario;
3. at least as accurate as ICP and more accurate than the particle filter on every scenario,
   the real logs included;
4. faster per update than both at equal beams (AMCL with every beam, every scan).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from bench.accuracy import ScenarioResult
from bench.measures import Summary
from bench.methods import DEFAULT_METHOD, Method
from bench.speed import Point


def _cm(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{100 * v:.2f}" if v < 0.1 else f"{100 * v:.1f}"


def _deg(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{math.degrees(v):.2f}"


def _pct(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{100 * v:.0f} %"


def _ms(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.2f}" if v < 10 else f"{v:.1f}"


def scenario_table(res: ScenarioResult, methods: Sequence[Method]) -> list[str]:
    """One scenario: a row per method."""
    runs = len(res.runs)
    updates = sum(r.updates for r in res.runs)
    bound = next(iter(res.summaries.values())).bound if res.summaries else math.nan
    note = " (reference: SLAM poses; bound with an assumed 2 cm range noise)" if res.real else ""
    lines = [
        f"**{res.name}**: {res.description}. {runs} run(s), {updates} updates; "
        f"Cramer-Rao bound (RMS over the scans) {1000 * bound:.2f} mm{note}.",
        "",
        "| method | RMSE cm | heading RMSE deg | p95 cm | within 5 cm and 2 deg "
        "| diverged runs | updates > 0.5 m | missing | lost | RMSE / bound "
        "| median ms | p99 ms | mean ms |",
        "| --- |" + " ---: |" * 12,
    ]
    for m in methods:
        s = res.summaries.get(m.name)
        if s is None:
            continue
        lines.append(
            f"| {m.label} | {_cm(s.rmse)} | {_deg(s.heading_rmse)} | {_cm(s.p95)} "
            f"| {_pct(s.within)} | {s.diverged_runs}/{s.runs} | {_pct(s.diverged_share)} "
            f"| {s.missing} | {_pct(s.lost)} | {s.ratio:.1f} | {_ms(s.median_ms)} "
            f"| {_ms(s.p99_ms)} | {_ms(s.mean_ms)} |"
        )
    return lines


def overview_table(results: Sequence[ScenarioResult], methods: Sequence[Method]) -> list[str]:
    """Translation RMSE (cm) of every method on every scenario, and the default's ratio."""
    head = "| scenario | bound mm | " + " | ".join(m.label for m in methods)
    head += f" | {DEFAULT_METHOD} RMSE / bound |"
    lines = [head, "| --- | ---: |" + " ---: |" * (len(methods) + 1)]
    for res in results:
        s0 = res.summaries.get(DEFAULT_METHOD)
        bound = s0.bound if s0 else math.nan
        cells = [
            _cm(res.summaries[m.name].rmse) if m.name in res.summaries else "-" for m in methods
        ]
        ratio = f"{s0.ratio:.1f}" if s0 else "-"
        lines.append(f"| {res.name} | {1000 * bound:.2f} | " + " | ".join(cells) + f" | {ratio} |")
    return lines


def _get(res: ScenarioResult, name: str) -> Summary | None:
    return res.summaries.get(name)


def targets(results: Sequence[ScenarioResult], speed: Sequence[Point]) -> list[str]:
    """The issue's targets for the default localizer: met or not, and by how much."""
    rows = ["| target | result | met |", "| --- | --- | --- |"]
    nominal = next((r for r in results if r.name == "nominal"), None)
    d = _get(nominal, DEFAULT_METHOD) if nominal else None
    if d is not None:
        rows.append(
            f"| RMSE <= 2 x bound (nominal) | {_cm(d.rmse)} cm vs bound {1000 * d.bound:.2f} mm: "
            f"{d.ratio:.1f} x | {'yes' if d.ratio <= 2.0 else 'no'} |"
        )
    div = [
        f"{r.name} {s.diverged_runs}/{s.runs}"
        for r in results
        if (s := _get(r, DEFAULT_METHOD)) and s.diverged_runs
    ]
    rows.append(
        "| no divergence in any scenario | "
        + ("none" if not div else "diverged runs: " + ", ".join(div))
        + f" | {'yes' if not div else 'no'} |"
    )
    for other, strict, what in (("icp", False, "ICP"), ("amcl", True, "AMCL")):
        worse = []
        for r in results:
            s, o = _get(r, DEFAULT_METHOD), _get(r, other)
            if s is None or o is None:
                continue
            if (s.rmse >= o.rmse) if strict else (s.rmse > o.rmse):
                worse.append(f"{r.name} {_cm(s.rmse)} vs {_cm(o.rmse)} cm")
        verb = "more accurate than" if strict else "at least as accurate as"
        rows.append(
            f"| {verb} {what} on every scenario | "
            + ("everywhere" if not worse else "not on: " + "; ".join(worse))
            + f" | {'yes' if not worse else 'no'} |"
        )
    beams = sorted({p.x for p in speed})
    slower = []
    for n in beams:
        at = {p.method: p for p in speed if p.x == n}
        if DEFAULT_METHOD not in at:
            continue
        mine = at[DEFAULT_METHOD].median_ms
        slower += [
            f"{n} beams: {_ms(mine)} vs {other} {_ms(at[other].median_ms)} ms"
            for other in ("icp", "amcl-all")
            if other in at and mine >= at[other].median_ms
        ]
    if beams:
        rows.append(
            "| faster per update than ICP and AMCL at equal beams (median) | "
            + ("at every beam count" if not slower else "not at: " + "; ".join(slower))
            + f" | {'yes' if not slower else 'no'} |"
        )
    return rows


def speed_tables(
    by_beams: Sequence[Point],
    by_map: Sequence[Point],
    fits: dict[str, tuple[float, float]],
    labels: dict[str, str],
) -> list[str]:
    """Latency against beams and against map size, and the fitted growth."""
    lines: list[str] = []
    for title, points in (("beams per scan", by_beams), ("map", by_map)):
        if not points:
            continue
        names = list(dict.fromkeys(p.method for p in points))
        settings = list(dict.fromkeys((p.x, p.label) for p in points))
        col = "walls" if title == "map" else "beams"
        lines += [
            f"Update latency against {title}: median / p99 ms (translation RMSE cm).",
            "",
            f"| {title} | {col} | " + " | ".join(labels.get(n, n) for n in names) + " |",
            "| --- | ---: |" + " --- |" * len(names),
        ]
        for x, label in settings:
            cells = []
            for n in names:
                p = next((q for q in points if q.method == n and q.x == x), None)
                cells.append(
                    "-" if p is None else f"{_ms(p.median_ms)} / {_ms(p.p99_ms)} ({_cm(p.rmse)})"
                )
            lines.append(f"| {label} | {x} | " + " | ".join(cells) + " |")
        lines.append("")
    if fits:
        lines += [
            "Fitted growth of the median latency with the beams per scan, "
            "`latency = a * beams^b` (log-log least squares; the paper claims "
            "O(n log(delta/epsilon)), b = 1):",
            "",
            "| method | a (ms) | b | updates per second per core at 360 beams (1 / median) |",
            "| --- | ---: | ---: | ---: |",
        ]
        for n, (a, b) in fits.items():
            at = next((p for p in by_beams if p.method == n and p.x == 360), None)
            rate = f"{1000.0 / at.median_ms:.0f}" if at and at.median_ms > 0 else "-"
            lines.append(f"| {labels.get(n, n)} | {a:.4f} | {b:.2f} | {rate} |")
    return lines
