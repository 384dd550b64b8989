"""Figures of the benchmark (matplotlib, Agg canvas; no display needed).

* ``trajectories-{scenario}.png``: the map, the reference path and each method's path on the
  scenario's first run.
* ``errors.png``: position error over time, one panel per scenario, log scale.
* ``rmse.png``: RMSE of each method per scenario beside the Cramer-Rao bound, log scale.
* ``latency-beams.png`` and ``latency-map.png``: median update latency (bars to the 99th
  percentile) against beams per scan and against the number of walls in the map.
* ``log-errors-{log}.png``: position error over the scans of a real log, every method, one
  panel per odometry variant (the log's own, and the made-up 5 % one), log scale.
* ``ellipses-{scenario}.png``: a simulated run's true path, the default's poses and every
  k-th pose's 3-sigma position ellipse on the map.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import shapely
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath

from bench.accuracy import ScenarioResult
from bench.measures import errors
from bench.scenarios import FloatArray
from bench.speed import Point
from rlutf.map import Map

#: Colour and line style per method; methods not listed are not drawn on trajectories.
STYLE = {
    "odometry": ("#8c8c8c", (0, (4, 2))),
    "paper": ("#e08a1e", "-"),
    "paper-area": ("#b5651d", (0, (3, 1))),
    "norefine": ("#6f9fe0", (0, (5, 1))),
    "default": ("#1f5fbf", "-"),
    "area": ("#1f5fbf", "-"),
    "turning": ("#9b59b6", "-"),
    "combined": ("#17a2b8", "-"),
    "icp": ("#2e9e44", "-"),
    "amcl": ("#d1495b", "-"),
    "amcl-60": ("#d1495b", "-"),
    "amcl-all": ("#7a1f2b", (0, (2, 1))),
}
LABEL = {
    "odometry": "dead reckoning",
    "paper": "RLuTF paper (turning)",
    "paper-area": "RLuTF paper, area",
    "norefine": "RLuTF default, no refinement",
    "default": "RLuTF default",
    "area": "RLuTF default (area)",
    "turning": "RLuTF turning",
    "combined": "RLuTF combined",
    "icp": "ICP point-to-line",
    "amcl": "AMCL",
    "amcl-60": "AMCL, every scan, 60 beams",
    "amcl-all": "AMCL, every scan, all beams",
}
TRAJECTORY_METHODS = ("odometry", "paper", "default", "icp", "amcl")


def _save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return path


def _draw_map(ax: Axes, world: Map) -> None:
    vertices, codes = [], []
    for poly in shapely.get_parts(shapely.orient_polygons(world.geometry)):
        for ring in (poly.exterior, *poly.interiors):
            xy = np.asarray(ring.coords)[:, :2]
            code = np.full(len(xy), MplPath.LINETO, dtype=np.uint8)
            code[0], code[-1] = MplPath.MOVETO, MplPath.CLOSEPOLY
            vertices.append(xy)
            codes.append(code)
    path = MplPath(np.vstack(vertices), np.concatenate(codes))
    ax.set_facecolor("#b7bec6")
    ax.add_patch(PathPatch(path, facecolor="#eef4fa", edgecolor="#1f2a36", linewidth=0.6))
    minx, miny, maxx, maxy = world.bounds
    ax.set_xlim(minx - 0.5, maxx + 0.5)
    ax.set_ylim(miny - 0.5, maxy + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def trajectories(result: ScenarioResult, path: Path) -> Path:
    """The first run of a scenario: map, reference path and each method's path."""
    run = result.runs[0]
    minx, miny, maxx, maxy = run.world.bounds
    aspect = (maxy - miny + 1.0) / (maxx - minx + 1.0)
    width = 8.0
    fig = Figure(figsize=(width, min(max(width * aspect, 3.0), 9.0) + 1.6), layout="constrained")
    ax = fig.add_subplot()
    _draw_map(ax, run.world)
    ax.plot(run.truth[:, 0], run.truth[:, 1], color="black", lw=2.2, label="reference", zorder=3)
    for name in TRAJECTORY_METHODS:
        traces = result.traces.get(name)
        if not traces:
            continue
        colour, style = STYLE[name]
        p = np.vstack([run.truth[:1], traces[0].poses])
        s = result.summaries[name]
        ax.plot(
            p[:, 0],
            p[:, 1],
            color=colour,
            ls=style,
            lw=1.1,
            zorder=4,
            label=f"{LABEL.get(name, name)} (RMSE {100 * s.rmse:.1f} cm)",
        )
    ax.plot(*run.truth[0, :2], "o", color="black", ms=6, zorder=5)
    ax.set_title("\n".join([result.name, *textwrap.wrap(result.description, 90)]), fontsize=9)
    fig.legend(loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    return _save(fig, path)


def error_panels(results: Sequence[ScenarioResult], methods: Sequence[str], path: Path) -> Path:
    """Position error over time on each scenario's first run, one panel per scenario."""
    cols = 3
    rows = math.ceil(len(results) / cols)
    fig = Figure(figsize=(13.0, 3.1 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax, res in zip(axes.ravel(), results, strict=False):
        run = res.runs[0]
        for name in methods:
            if name not in res.traces:
                continue
            colour, style = STYLE.get(name, ("black", "-"))
            err, _ = errors(res.traces[name][0].poses, run.truth[1:])
            ax.plot(
                np.maximum(err, 1e-4), color=colour, ls=style, lw=0.9, label=LABEL.get(name, name)
            )
        if res.bounds and len(res.bounds[0]):
            ax.plot(res.bounds[0], color="black", lw=0.8, ls=":", label="Cramer-Rao bound")
        ax.set_yscale("log")
        ax.set_ylim(1e-4, 30.0)
        ax.set_title(res.name, fontsize=10)
        ax.set_xlabel("update")
        ax.set_ylabel("position error [m]")
        ax.grid(True, which="major", alpha=0.3)
    for ax in axes.ravel()[len(results) :]:
        ax.set_visible(False)
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0.0, 0.04, 1.0, 1.0))
    return _save(fig, path)


def rmse_bars(results: Sequence[ScenarioResult], methods: Sequence[str], path: Path) -> Path:
    """RMSE per scenario and method (log scale), with each scenario's bound as a black tick."""
    fig = Figure(figsize=(13.0, 4.6))
    ax = fig.add_subplot()
    width = 0.8 / len(methods)
    x = np.arange(len(results))
    for i, name in enumerate(methods):
        vals = [res.summaries[name].rmse if name in res.summaries else np.nan for res in results]
        colour, _ = STYLE.get(name, ("black", "-"))
        ax.bar(x - 0.4 + (i + 0.5) * width, vals, width, color=colour, label=LABEL.get(name, name))
    bounds = [res.summaries[methods[0]].bound for res in results]
    ax.scatter(x, bounds, marker="_", s=900, color="black", zorder=5, label="Cramer-Rao bound")
    ax.set_yscale("log")
    ax.set_xticks(x, [res.name for res in results])
    ax.set_ylabel("translation RMSE [m]")
    ax.grid(True, axis="y", which="major", alpha=0.3)
    ax.legend(fontsize=8, ncol=4, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


def latency(
    points: Sequence[Point],
    path: Path,
    xlabel: str,
    fits: dict[str, tuple[float, float]] | None = None,
) -> Path:
    """Median latency (bars to p99) of each method against the swept value, log-log."""
    fig = Figure(figsize=(8.0, 5.0))
    ax = fig.add_subplot()
    for name in dict.fromkeys(p.method for p in points):
        pts = sorted((p for p in points if p.method == name), key=lambda p: p.x)
        xs = np.array([p.x for p in pts], dtype=np.float64)
        med = np.array([p.median_ms for p in pts])
        p99 = np.array([p.p99_ms for p in pts])
        colour, style = STYLE.get(name, ("black", "-"))
        label = LABEL.get(name, name)
        if fits and name in fits:
            _, b = fits[name]
            label += f" (slope {b:.2f})"
        ax.errorbar(
            xs,
            med,
            yerr=[np.zeros_like(med), p99 - med],
            color=colour,
            ls=style,
            marker="o",
            ms=4,
            capsize=3,
            lw=1.2,
            label=label,
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("update latency [ms] (median, bar to p99)")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="best", framealpha=0.9)
    fig.tight_layout()
    return _save(fig, path)


def log_errors(
    variants: Sequence[ScenarioResult], methods: Sequence[str], path: Path, title: str
) -> Path:
    """Position error over the scans of one real log: a panel per odometry variant."""
    fig = Figure(figsize=(15.0, 3.6 * len(variants)))
    axes = fig.subplots(len(variants), 1, squeeze=False)[:, 0]
    for ax, res in zip(axes, variants, strict=True):
        run = res.runs[0]
        for name in methods:
            if name not in res.traces:
                continue
            colour, style = STYLE.get(name, ("black", "-"))
            err, _ = errors(res.traces[name][0].poses, run.truth[1:])
            s = res.summaries[name]
            ax.plot(
                np.arange(1, len(err) + 1),
                np.maximum(err, 1e-3),
                color=colour,
                ls=style,
                lw=0.9,
                label=f"{LABEL.get(name, name)} (RMSE {_short(s.rmse)}, max {_short(s.max_error)})",
            )
        ax.axhline(0.5, color="#d1495b", lw=0.8, ls=":", label="0.5 m (diverged)")
        ax.set_yscale("log")
        ax.set_ylim(1e-3, 100.0)
        ax.set_xlim(0, run.updates + 1)
        ax.set_title(f"{res.name}: {res.description}", fontsize=9)
        ax.set_xlabel("scan index")
        ax.set_ylabel("position error [m]")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def _short(v: float) -> str:
    if not math.isfinite(v):
        return "-"
    return f"{100 * v:.1f} cm" if v < 1.0 else f"{v:.1f} m"


def ellipse_scale(covariances: FloatArray, visible: float = 0.15) -> float:
    """A whole-number factor that makes the median 3-sigma semi-major axis about ``visible``
    metres (1 when they are already that big)."""
    xy = covariances[:, :2, :2]
    ok = np.isfinite(xy).all(axis=(1, 2))
    if not ok.any():
        return 1.0
    major = 3.0 * np.sqrt(np.maximum(np.linalg.eigvalsh(xy[ok])[:, -1], 0.0))
    med = float(np.median(major))
    if med <= 0.0 or med >= visible:
        return 1.0
    return float(10 ** math.ceil(math.log10(visible / med)))


def ellipses(result: ScenarioResult, path: Path, method: str = "default", every: int = 10) -> Path:
    """A run's true path, ``method``'s poses and every ``every``-th 3-sigma position ellipse."""
    run = result.runs[0]
    trace = result.traces[method][0]
    covs = trace.covariances
    minx, miny, maxx, maxy = run.world.bounds
    aspect = (maxy - miny + 1.0) / (maxx - minx + 1.0)
    fig = Figure(figsize=(9.0, min(max(9.0 * aspect, 3.0), 9.0) + 1.4), layout="constrained")
    ax = fig.add_subplot()
    _draw_map(ax, run.world)
    ax.plot(run.truth[:, 0], run.truth[:, 1], color="black", lw=1.6, label="true path", zorder=3)
    colour = STYLE.get(method, ("#1f5fbf", "-"))[0]
    ax.plot(
        *trace.poses[:, :2].T,
        ".",
        color=colour,
        ms=2.5,
        label=f"{LABEL.get(method, method)} poses",
        zorder=4,
    )
    scale = 1.0
    drawn = 0
    if covs is not None:
        scale = ellipse_scale(covs)
        t = np.linspace(0.0, 2.0 * math.pi, 60)
        circle = np.stack([np.cos(t), np.sin(t)])
        for k in range(0, len(covs), every):
            c = covs[k, :2, :2]
            if not (np.isfinite(c).all() and np.isfinite(trace.poses[k]).all()):
                continue
            w, v = np.linalg.eigh(c)
            pts = (v @ (3.0 * scale * np.sqrt(np.maximum(w, 0.0))[:, None] * circle)).T
            # Ellipse and error enlarged alike: centred at truth + scale * (estimate - truth),
            # so whether the true pose (black dot) lies inside reads at any scale.
            true_xy = run.truth[k + 1, :2]
            pts += true_xy + scale * (trace.poses[k, :2] - true_xy)
            ax.plot(
                pts[:, 0],
                pts[:, 1],
                color="#d1495b",
                lw=1.0,
                zorder=5,
                label="3-sigma position ellipse" if drawn == 0 else None,
            )
            ax.plot(
                *true_xy,
                "o",
                color="black",
                ms=2.5,
                zorder=6,
                label="true position at that update" if drawn == 0 else None,
            )
            drawn += 1
    enlarged = f", ellipse and error drawn {scale:g} x enlarged" if scale != 1.0 else ", true size"
    note = "no covariance given" if covs is None else f"every {every}th update{enlarged}"
    ax.set_title(
        f"{result.name}, run seed {run.seed}: {LABEL.get(method, method)}, 3-sigma position "
        f"ellipses ({note})",
        fontsize=9,
    )
    fig.legend(loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    return _save(fig, path)
