"""A robot's status as a Foxglove scene entity: its 1-sigma ellipse and a label.

The live view (:mod:`service.live.foxview`) draws one entity per robot on ``/foxglove/fleet``
(``foxglove.SceneUpdate``, the schema the log's map views use; the robots that moved since the
last refresh in one message): a flat ellipse of the pose's
1-sigma position uncertainty (from the PoseEstimate's covariance; none without one), coloured by
status, and a text label such as ``r1 tracking ±2.1 cm ±0.4°``. Pure: JSON in, JSON out.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

from service.logs.foxglove import robot_frame, scene_entity

#: Status colours: tracking green, corrected blue, lost red, relocalizing orange.
COLORS = {
    "tracking": {"r": 0.1, "g": 0.7, "b": 0.2, "a": 0.6},
    "corrected": {"r": 0.1, "g": 0.4, "b": 0.9, "a": 0.6},
    "lost": {"r": 0.9, "g": 0.1, "b": 0.1, "a": 0.6},
    "relocalizing": {"r": 1.0, "g": 0.6, "b": 0.0, "a": 0.6},
}
_TEXT_COLOR = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}
#: The ellipse is drawn at least this wide, m, so a very certain pose stays visible.
_MIN_DIAMETER = 0.05
_FLAT = 0.01


def sigma_ellipse(cov: list[float]) -> tuple[float, float, float]:
    """The 1-sigma ellipse of a 3x3 row-major x, y, theta covariance: semi-axes (m), angle (rad).

    The semi-axes are the square roots of the xy block's eigenvalues, larger first; the angle is
    the larger axis' direction.
    """
    a, b, d = cov[0], cov[1], cov[4]
    mid, half = (a + d) / 2, math.hypot((a - d) / 2, b)
    major, minor = math.sqrt(max(mid + half, 0.0)), math.sqrt(max(mid - half, 0.0))
    return major, minor, 0.5 * math.atan2(2 * b, a - d)


def status_of(pose: dict[str, Any]) -> str:
    """``relocalizing`` while hypotheses are given, else the pose's own status."""
    return "relocalizing" if pose.get("hypotheses") else str(pose["status"])


def label(robot: str, pose: dict[str, Any]) -> str:
    """``r1 tracking ±2.1 cm ±0.4°`` (the 1-sigma position and heading, when known)."""
    status = status_of(pose)
    if status == "relocalizing":
        status += f" ({len(pose['hypotheses'])} hypotheses)"
    cov = pose.get("covariance")
    if not cov:
        return f"{robot} {status}"
    major, _, _ = sigma_ellipse(cov)
    heading = math.degrees(math.sqrt(max(cov[8], 0.0)))
    return f"{robot} {status} ±{major * 100:.1f} cm ±{heading:.1f}°"


def _primitive_pose(x: float, y: float, yaw: float) -> dict[str, Any]:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
    }


def status_entity(robot: str, pose: dict[str, Any], frame: str) -> dict[str, Any]:
    """The scene entity of a decoded PoseEstimate, in the map frame ``frame``."""
    stamp = int(pose["stamp_ns"])
    x, y = float(pose["x"]), float(pose["y"])
    color = COLORS.get(status_of(pose), COLORS["lost"])
    cylinders = []
    cov = pose.get("covariance")
    if cov:
        major, minor, angle = sigma_ellipse(cov)
        cylinders.append(
            {
                "pose": _primitive_pose(x, y, angle),
                "size": {
                    "x": max(2 * major, _MIN_DIAMETER),
                    "y": max(2 * minor, _MIN_DIAMETER),
                    "z": _FLAT,
                },
                "bottom_scale": 1.0,
                "top_scale": 1.0,
                "color": color,
            }
        )
    text = {
        "pose": _primitive_pose(x, y + 0.3, 0.0),
        "billboard": True,
        "font_size": 14.0,
        "scale_invariant": True,
        "color": _TEXT_COLOR,
        "text": label(robot, pose),
    }
    metadata = {"robot_id": robot, "status": status_of(pose), "base_frame": robot_frame(robot)}
    return scene_entity(
        stamp, frame, f"robot/{robot}", metadata, False, cylinders=cylinders, texts=[text]
    )


def status_update(
    entities: list[dict[str, Any]], deleted: Sequence[str] = (), stamp_ns: int = 0
) -> bytes:
    """One ``foxglove.SceneUpdate`` of several robots' entities (each replaces its robot's),
    deleting the entities of ids ``deleted`` (robots gone) as of ``stamp_ns``."""
    stamp = {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}
    deletions = [{"timestamp": stamp, "type": 0, "id": d} for d in deleted]
    update = {"deletions": deletions, "entities": entities}
    return json.dumps(update, separators=(",", ":"), allow_nan=False).encode()


#: Map health in the live view: something the map lacks, and map walls beams pass through.
CHANGE_COLORS = {
    "added": {"r": 1.0, "g": 0.55, "b": 0.0, "a": 1.0},
    "removed": {"r": 0.9, "g": 0.1, "b": 0.9, "a": 1.0},
}
_CHANGE_THICKNESS = 0.08


def _rings(kind: str, geometry: dict[str, Any]) -> list[list[list[float]]]:
    """The point lists to draw of a change's geometry (polygon outlines, or lines)."""
    coords = geometry.get("coordinates", [])
    gtype = geometry.get("type")
    if gtype == "Polygon":
        return [list(coords[0])] if coords else []
    if gtype == "MultiPolygon":
        return [list(p[0]) for p in coords if p]
    if gtype == "LineString":
        return [list(coords)]
    if gtype == "MultiLineString":
        return [list(line) for line in coords]
    return []


def maphealth_update(health: dict[str, Any], frame: str) -> bytes:
    """A ``foxglove.SceneUpdate`` of a decoded MapHealth: each change outlined in its kind's
    colour (``added`` orange, ``removed`` magenta) with a label (kind, confidence, robots)."""
    map_id = str(health["map_id"])
    stamp = int(health["stamp_ns"])
    lines, texts = [], []
    for change in health.get("changes", []):
        kind = str(change.get("kind"))
        color = CHANGE_COLORS.get(kind, _TEXT_COLOR)
        for ring in _rings(kind, change.get("geometry", {})):
            points = [{"x": float(p[0]), "y": float(p[1]), "z": 0.0} for p in ring]
            if len(points) < 2:
                continue
            lines.append(
                {
                    "type": 0,
                    "pose": _primitive_pose(0.0, 0.0, 0.0),
                    "thickness": _CHANGE_THICKNESS,
                    "scale_invariant": False,
                    "points": points,
                    "color": color,
                    "colors": [],
                    "indices": [],
                }
            )
            x, y = points[0]["x"], points[0]["y"]
            texts.append(
                {
                    "pose": _primitive_pose(x, y + 0.3, 0.0),
                    "billboard": True,
                    "font_size": 12.0,
                    "scale_invariant": True,
                    "color": color,
                    "text": f"{kind} {100 * float(change.get('confidence', 0.0)):.0f} % "
                    f"({change.get('robots', 0)} robots)",
                }
            )
    metadata = {"map_id": map_id, "version": str(health.get("version", ""))}
    entity = scene_entity(
        stamp, frame, f"maphealth/{map_id}", metadata, True, lines=lines, texts=texts
    )
    return json.dumps(
        {"deletions": [], "entities": [entity]}, separators=(",", ":"), allow_nan=False
    ).encode()
