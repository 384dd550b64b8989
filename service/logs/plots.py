"""Per-robot trajectory figures of a replay (matplotlib, Agg; no display needed).

Each figure shows the robot's map, its recorded poses, the recomputed ones, and dead reckoning:
the odometry motion composed onto the robot's initial pose (re-anchored at every new initial
pose), which is where the robot would think it is with no correction.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from rlutf.motion import compose, relative
from schemas import Map, SchemaError, decode
from service.logs.posematch import PoseRecord
from service.logs.replay import ReplayResult

FloatArray = np.ndarray


def dead_reckoning(
    odometry: Sequence[tuple[int, float, float, float]],
    initial_poses: Sequence[tuple[int, str, float, float, float]],
) -> FloatArray:
    """Odometry anchored at the initial poses: ``(K, 3)`` map poses, one per odometry reading.

    A reading is placed relative to the latest initial pose at or before it, through the
    odometry pose at that initial pose (the last reading at or before its stamp, else the first
    after it). Readings before the first initial pose are left out.
    """
    odom = sorted(odometry)
    if not odom or not initial_poses:
        return np.empty((0, 3))
    stamps = [o[0] for o in odom]
    poses = np.array([o[1:] for o in odom], dtype=np.float64)
    anchors = sorted(initial_poses)
    anchor_stamps = [a[0] for a in anchors]
    out = []
    for k, stamp in enumerate(stamps):
        i = bisect.bisect_right(anchor_stamps, stamp) - 1
        if i < 0:
            continue
        a_stamp, _, x, y, theta = anchors[i]
        j = max(bisect.bisect_right(stamps, a_stamp) - 1, 0)
        out.append(compose((x, y, theta), relative(poses[j], poses[k])))
    return np.array(out).reshape(-1, 3)


def _rings(payload: bytes) -> list[FloatArray]:
    try:
        msg = decode(Map, payload, max_bytes=1 << 30)
    except SchemaError:
        return []
    geometry = msg.geometry.model_dump(mode="python")
    polygons = (
        [geometry["coordinates"]]
        if geometry["type"] == "Polygon"
        else list(geometry["coordinates"])
    )
    return [np.asarray(ring, dtype=np.float64)[:, :2] for rings in polygons for ring in rings]


def _xy(poses: Sequence[PoseRecord]) -> FloatArray:
    return np.array([(p.x, p.y) for p in poses], dtype=np.float64).reshape(-1, 2)


def _draw(ax: Any, result: ReplayResult, robot: str, legend: bool) -> FloatArray:
    """Draw map and trajectories on ``ax``; return every trajectory point ``(K, 2)``."""
    recorded = result.recorded.get(robot, [])
    recomputed = result.recomputed.get(robot, [])
    initial = result.initial_poses.get(robot, [])
    map_ids = [p.map_id for p in (*recorded, *recomputed)] + [i[1] for i in initial]
    if map_ids and map_ids[-1] in result.maps:
        for i, ring in enumerate(_rings(result.maps[map_ids[-1]])):
            ax.plot(
                ring[:, 0],
                ring[:, 1],
                color="0.25",
                lw=1.0,
                label=f"map {map_ids[-1]}" if i == 0 else None,
            )
    points = [np.empty((0, 2))]
    dr = dead_reckoning(result.odometry.get(robot, []), initial)
    if len(dr):
        ax.plot(dr[:, 0], dr[:, 1], ":", color="tab:gray", lw=1.8, label="dead reckoning")
        points.append(dr[:, :2])
    for poses, style, color, width, name in (
        (recorded, "-", "tab:blue", 3.0, "recorded"),
        (recomputed, "--", "tab:orange", 1.4, "recomputed"),
    ):
        if poses:
            xy = _xy(poses)
            ax.plot(
                xy[:, 0],
                xy[:, 1],
                style,
                color=color,
                lw=width,
                alpha=0.75,
                label=f"{name} ({len(poses)})",
            )
            points.append(xy)
    for k, (_, _, x, y, theta) in enumerate(initial):
        ax.plot([x], [y], "o", color="tab:green", ms=6, label="initial pose" if k == 0 else None)
        ax.annotate(
            "",
            (x + 0.4 * np.cos(theta), y + 0.4 * np.sin(theta)),
            (x, y),
            arrowprops={"arrowstyle": "->", "color": "tab:green"},
        )
        points.append(np.array([[x, y]]))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.3)
    if legend:
        ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return np.concatenate(points)


def plot_robot(result: ReplayResult, robot: str, path: Path) -> Path:
    """Write one robot's figure to ``path`` (PNG): the whole map, and a zoom on the path."""
    fig = Figure(figsize=(12.0, 5.5), dpi=100)
    FigureCanvasAgg(fig)
    whole, zoom = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.3, 1.0]})
    _draw(whole, result, robot, legend=False)
    whole.set_title("whole map")
    points = _draw(zoom, result, robot, legend=True)
    if len(points):
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2 + 0.5, 1.0)
        zoom.set_xlim(centre[0] - half, centre[0] + half)
        zoom.set_ylim(centre[1] - half, centre[1] + half)
        zoom.set_aspect("equal", adjustable="box")
        whole.add_patch(
            Rectangle(
                (centre[0] - half, centre[1] - half),
                2 * half,
                2 * half,
                fill=False,
                ec="tab:red",
                lw=1.0,
                ls="--",
            )
        )
    zoom.set_title("trajectory (zoomed)")
    fig.suptitle(f"robot {robot}: recorded, recomputed and dead-reckoned poses")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def plot_all(result: ReplayResult, out_dir: Path) -> list[Path]:
    """One PNG per robot, ``{out_dir}/{robot}.png``."""
    robots = sorted(set(result.recorded) | set(result.recomputed) | set(result.initial_poses))
    return [plot_robot(result, robot, out_dir / f"{robot}.png") for robot in robots]
