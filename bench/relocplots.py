"""Figures of the relocalization benchmark (:mod:`bench.relocalize`; matplotlib, Agg).

* ``relocalize-hypotheses.png``: per case, the map, each hypothesis as an arrow and the scan's
  points drawn from it, its score in the legend; the truth as a black arrow.
* ``relocalize-kidnap.png``: a kidnapped run's position error per scan (log scale), each
  update coloured by its status, the kidnap drawn.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from bench.kidnap import KidnapRun
from bench.plots import _draw_map, _save
from rlutf.map import Map
from rlutf.raycast import Beams
from rlutf.relocalize import Relocalization
from rlutf.scan import Scan, beam_points

#: Colours of the hypotheses, best first.
COLOURS = ("#1f5fbf", "#d1495b", "#2e9e44", "#e08a1e", "#9b59b6", "#17a2b8", "#8c564b", "#7f7f7f")
STATUS = {
    "tracking": ("#2e9e44", "o"),
    "corrected": ("#1f5fbf", "s"),
    "lost": ("#d1495b", "x"),
}

Picture = tuple[str, Map, Scan, np.ndarray, Relocalization]


def _scan_at(scan: Scan, pose: np.ndarray) -> np.ndarray:
    """The scan's points in the map frame, the robot at ``pose``."""
    valid = scan.valid()
    beams = Beams.of(scan.angles).select(valid)
    local = beam_points(scan.ranges[valid], beams.cos, beams.sin, scan.sensor_offset)
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    x = pose[0] + c * local[:, 0] - s * local[:, 1]
    y = pose[1] + s * local[:, 0] + c * local[:, 1]
    return np.column_stack([x, y])


def _arrow(ax, pose: np.ndarray, colour: str, length: float, width: float) -> None:  # type: ignore[no-untyped-def]
    ax.annotate(
        "",
        xy=(pose[0] + length * math.cos(pose[2]), pose[1] + length * math.sin(pose[2])),
        xytext=(pose[0], pose[1]),
        arrowprops={"arrowstyle": "-|>", "color": colour, "lw": width},
        zorder=6,
    )


def hypotheses(pictures: Sequence[Picture], path: Path, most: int = 6) -> Path:
    """Each case: the map, the hypotheses (at most ``most``) as arrows and the scan drawn from
    each, the truth in black."""
    heights = []
    for _, world, _, _, _ in pictures:
        minx, miny, maxx, maxy = world.bounds
        heights.append(min(max(9.0 * (maxy - miny + 1.0) / (maxx - minx + 1.0), 2.5), 9.0) + 0.6)
    fig = Figure(figsize=(13.0, sum(heights)), layout="constrained")
    axes = fig.subplots(len(pictures), 1, squeeze=False, height_ratios=heights)[:, 0]
    for ax, (title, world, scan, truth, result) in zip(axes, pictures, strict=True):
        _draw_map(ax, world)
        minx, miny, maxx, maxy = world.bounds
        size = max(maxx - minx, maxy - miny)
        length = max(0.04 * size, 0.4)
        for k, h in enumerate(result.hypotheses[:most]):
            colour = COLOURS[k % len(COLOURS)]
            pts = _scan_at(scan, h.pose)
            off = math.hypot(*(h.pose[:2] - truth[:2]))
            turn = math.degrees(abs((h.pose[2] - truth[2] + math.pi) % (2 * math.pi) - math.pi))
            where = "at the truth" if off < 0.3 and turn < 5 else f"{off:.1f} m, {turn:.0f} deg off"
            ax.scatter(
                pts[:, 0],
                pts[:, 1],
                s=3 if k else 5,
                color=colour,
                alpha=0.9 if k == 0 else 0.6,
                zorder=5 - 0.1 * k,
                label=f"#{k + 1} score {h.score:.2f} ({where})",
            )
            _arrow(ax, h.pose, colour, length, 1.6)
        _arrow(ax, truth, "black", 0.7 * length, 1.0)
        ax.plot([], [], color="black", label="truth")
        verdict = (
            "ambiguous"
            if result.ambiguous
            else ("found (corrected)" if result.found else "not found")
        )
        ax.set_title(f"{title}: relocalize() says {verdict}", fontsize=10)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    return _save(fig, path)


def kidnap(run: KidnapRun, path: Path) -> Path:
    """A kidnapped run: position error per scan, log scale, status marked, kidnap drawn."""
    fig = Figure(figsize=(11.0, 4.2), layout="constrained")
    ax = fig.add_subplot()
    k = np.arange(1, len(run.errors))
    err = np.maximum(run.errors[1:], 1e-5)
    ax.plot(k, err, color="#8c8c8c", lw=0.8, zorder=2)
    statuses = np.array(run.statuses[1:])
    for name, (colour, marker) in STATUS.items():
        m = statuses == name
        if m.any():
            ax.scatter(k[m], err[m], color=colour, marker=marker, s=16, zorder=3, label=name)
    reloc = run.relocalizing[1:]
    if reloc.any():
        ax.scatter(
            k[reloc],
            np.full(int(reloc.sum()), 2.5e-5),
            color="#e08a1e",
            marker="|",
            s=60,
            label="relocalizing (searching or following hypotheses)",
        )
    ax.axvline(run.at, color="black", lw=1.2, ls="--", label=f"kidnap (scan {run.at})")
    if run.recovered is not None:
        back = run.at + run.recovered - 1
        label = f"back within 5 cm and 1 deg ({run.recovered} scans)"
        ax.axvline(back, color="#2e9e44", lw=1.0, ls=":", label=label)
    ax.axhline(0.05, color="#1f5fbf", lw=0.8, ls=":", label="5 cm")
    ax.axhline(0.3, color="#d1495b", lw=0.8, ls=":", label="0.3 m (wrong if not lost)")
    ax.set_yscale("log")
    ax.set_ylim(1e-5, max(100.0, float(err.max()) * 2))
    ax.set_xlim(0, len(run.errors))
    ax.set_xlabel("scan index")
    ax.set_ylabel("position error [m]")
    ax.grid(True, which="major", alpha=0.3)
    ax.set_title(
        f"Kidnapped robot, building {run.area:.0f} m2, seed {run.seed}: Localizer error per scan",
        fontsize=10,
    )
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    return _save(fig, path)
