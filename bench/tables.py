"""Markdown of the accuracy and speed sections of ``BENCHMARKS.md``, and the issue's targets.

Targets (issue 11), checked on the default localizer (``LocalizerConfig()``):

1. translation RMSE at most 1.5 times the Cramer-Rao bound on every simulated scenario;
2. RMSE at most ICP's on every simulated scenario and on the real logs (both odometry
   variants);
3. no divergence (no update over 0.5 m off) anywhere;
4. mean NEES within [2, 4] (chi-square, 3 dof) on every simulated scenario;
5. median update at most 0.3 ms at 360 beams on the simulated building and at most 1 ms on
   the ACES map (speed section; the p99 is shown beside it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from bench.accuracy import ScenarioResult
from bench.measures import Summary
from bench.methods import DEFAULT_METHOD, Method
from bench.speed import Point


def cm(v: float) -> str:
    """Metres as centimetres for a table ("-" for none)."""
    return "-" if not math.isfinite(v) else f"{100 * v:.2f}" if v < 0.1 else f"{100 * v:.1f}"


def deg(v: float) -> str:
    """Radians as degrees for a table."""
    return "-" if not math.isfinite(v) else f"{math.degrees(v):.2f}"


def pct(v: float) -> str:
    """A share as a percentage for a table."""
    return "-" if not math.isfinite(v) else f"{100 * v:.0f} %"


def _nees(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.2f}" if v < 100 else f"{v:.3g}"


def _yes(ok: bool) -> str:
    return "yes" if ok else "no"


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
        "| diverged runs | updates > 0.5 m | max error cm | missing | lost | RMSE / bound "
        "| NEES | median ms | p99 ms | mean ms |",
        "| --- |" + " ---: |" * 14,
    ]
    for m in methods:
        s = res.summaries.get(m.name)
        if s is None:
            continue
        lines.append(
            f"| {m.label} | {cm(s.rmse)} | {deg(s.heading_rmse)} | {cm(s.p95)} "
            f"| {pct(s.within)} | {s.diverged_runs}/{s.runs} | {pct(s.diverged_share)} "
            f"| {cm(s.max_error)} | {s.missing} | {pct(s.lost)} | {s.ratio:.1f} "
            f"| {_nees(s.nees)} | {_ms(s.median_ms)} | {_ms(s.p99_ms)} | {_ms(s.mean_ms)} |"
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
            cm(res.summaries[m.name].rmse) if m.name in res.summaries else "-" for m in methods
        ]
        ratio = f"{s0.ratio:.1f}" if s0 else "-"
        lines.append(f"| {res.name} | {1000 * bound:.2f} | " + " | ".join(cells) + f" | {ratio} |")
    return lines


def _get(res: ScenarioResult, name: str) -> Summary | None:
    return res.summaries.get(name)


#: The targets' thresholds.
BOUND_RATIO = 1.5
NEES_RANGE = (2.0, 4.0)
BUILDING_MS = 0.3
ACES_MS = 1.0
DIVERGED_M = 0.5


def targets(
    results: Sequence[ScenarioResult],
    by_beams: Sequence[Point] = (),
    by_map: Sequence[Point] = (),
    default: str = DEFAULT_METHOD,
) -> list[str]:
    """The issue's targets for the default localizer: the measured numbers and met or not.

    Args:
        results: the accuracy results (simulated and real).
        by_beams: the speed section's latency against beams (the simulated building).
        by_map: its latency against map size (the ACES map among them in the full profile).
        default: the method checked.
    """
    rows = ["| target | result | met |", "| --- | --- | --- |"]
    sim = [(r, s) for r in results if not r.real and (s := _get(r, default)) is not None]
    real = [(r, s) for r in results if r.real and (s := _get(r, default)) is not None]

    def row(target: str, parts: Sequence[str], ok: bool, empty: str = "not measured") -> None:
        rows.append(f"| {target} | {'; '.join(parts) if parts else empty} | {_yes(ok)} |")

    ratios = [f"{r.name} {s.ratio:.2f} x" for r, s in sim]
    row(
        f"RMSE <= {BOUND_RATIO:g} x Cramer-Rao bound on every simulated scenario",
        ratios,
        bool(sim) and all(s.ratio <= BOUND_RATIO for _, s in sim),
    )
    for label, group in (("simulated scenario", sim), ("real log (both odometry variants)", real)):
        parts, ok = [], bool(group)
        for r, s in group:
            o = _get(r, "icp")
            if o is None:
                parts.append(f"{r.name}: no ICP run")
                ok = False
                continue
            fine = s.rmse <= o.rmse
            ok &= fine
            text = f"{r.name} {cm(s.rmse)} vs {cm(o.rmse)} cm{'' if fine else ' (no)'}"
            beaten = [
                m for m, t in r.summaries.items() if m != "odometry" and t.max_error <= DIVERGED_M
            ]
            if r.real and not beaten:
                text += " (this odometry defeats every method: all diverge)"
            parts.append(text)
        row(f"RMSE at most ICP's on every {label}", parts, ok)
    everywhere = sim + real
    worst = [f"{r.name} {cm(s.max_error)}" for r, s in everywhere]
    row(
        f"no divergence: no update over {DIVERGED_M:g} m anywhere (largest error, cm)",
        worst,
        bool(everywhere) and all(s.max_error <= DIVERGED_M for _, s in everywhere),
    )
    lo, hi = NEES_RANGE
    row(
        f"mean NEES in [{lo:g}, {hi:g}] on every simulated scenario",
        [f"{r.name} {_nees(s.nees)}" for r, s in sim],
        bool(sim) and all(lo <= s.nees <= hi for _, s in sim),
    )
    at = next((p for p in by_beams if p.method == default and p.x == 360), None)
    row(
        f"median update <= {BUILDING_MS:g} ms at 360 beams, simulated building (p99 beside)",
        [] if at is None else [f"median {at.median_ms:.3f} ms, p99 {at.p99_ms:.3f} ms"],
        at is not None and at.median_ms <= BUILDING_MS,
    )
    aces = next((p for p in by_map if p.method == default and p.label.startswith("aces")), None)
    row(
        f"median update <= {ACES_MS:g} ms on the ACES map, 360 beams (p99 beside)",
        [] if aces is None else [f"median {aces.median_ms:.3f} ms, p99 {aces.p99_ms:.3f} ms"],
        aces is not None and aces.median_ms <= ACES_MS,
        empty="not measured (the quick profile has no real maps in the speed sweep)",
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
                    "-" if p is None else f"{_ms(p.median_ms)} / {_ms(p.p99_ms)} ({cm(p.rmse)})"
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
