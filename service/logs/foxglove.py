"""Foxglove views of logged messages, so a log opens in Foxglove showing map, scans and poses.

Beside every ``rlutf.*`` message the log carries, a writer with a converter (replay, ``rlutf log
views``, the live recorder with ``record_views``) logs (same ``log_time``):

=================================== =========================== ==============================
topic                               schema                      from
=================================== =========================== ==============================
``/foxglove/maps/{map_id}``         ``foxglove.SceneUpdate``    Map: one line strip per ring
``/foxglove/robots/{robot}/scan``   ``foxglove.LaserScan``      LaserScan, in ``{robot}/base_link``
``/foxglove/robots/{robot}/pose``   ``foxglove.PoseInFrame``    PoseEstimate, in the map frame
``/foxglove/robots/{robot}/initialpose`` ``foxglove.PoseInFrame`` InitialPose, in the map frame
``/foxglove/tf``                    ``foxglove.FrameTransform`` PoseEstimate and InitialPose:
                                                                map frame -> ``{robot}/base_link``
=================================== =========================== ==============================

The map frame is the Map's ``frame_id`` (``map`` by default). A scan sits in the robot's base
frame, offset by its ``sensor_offset``; a beam with no return is written as range 0 (JSON has
no NaN, and Foxglove draws every range of a ``foxglove.LaserScan``), which puts it on the
sensor. The schemas are Foxglove's own (npm ``@foxglove/schemas``), embedded under
``service/logs/foxglove_schemas/`` so the service needs no npm at run time. Regenerate them with
``python -m service.logs.foxglove DIR`` (installs the npm package into ``DIR``);
``tests/service/logs/test_foxglove.py`` checks they still equal the package's.
"""

from __future__ import annotations

import json
import logging
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from service.logs.mcapfile import Record

log = logging.getLogger(__name__)

LASER_SCAN = "foxglove.LaserScan"
POSE_IN_FRAME = "foxglove.PoseInFrame"
FRAME_TRANSFORM = "foxglove.FrameTransform"
SCENE_UPDATE = "foxglove.SceneUpdate"
SCHEMA_NAMES = (LASER_SCAN, POSE_IN_FRAME, FRAME_TRANSFORM, SCENE_UPDATE)
TF_TOPIC = "/foxglove/tf"
DEFAULT_FRAME = "map"
#: A Map's ``frame_id`` in its JSON (a map has no other string field of that name).
_FRAME_ID = re.compile(rb'"frame_id"\s*:\s*("(?:[^"\\]|\\.)*")')

_WALL_COLOR = {"r": 0.15, "g": 0.15, "b": 0.15, "a": 1.0}
_OBSTACLE_COLOR = {"r": 0.75, "g": 0.3, "b": 0.1, "a": 1.0}
_WALL_THICKNESS = 0.05


#: The start of a LaserScan's ``ranges`` member in its JSON text.
_RANGES = re.compile(rb'"ranges"\s*:\s*\[')
#: The bytes a JSON array of numbers and nulls is made of, besides its brackets.
_NUMBERS_AND_NULLS = b"0123456789-+.eEnul, \t\r\n"


def robot_frame(robot: str) -> str:
    """The Foxglove frame of a robot's base."""
    return f"{robot}/base_link"


def _time(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(x: float, y: float, theta: float) -> dict[str, Any]:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)},
    }


def scene_entity(
    stamp_ns: int,
    frame: str,
    entity_id: str,
    metadata: dict[str, str],
    frame_locked: bool,
    **primitives: list[dict[str, Any]],
) -> dict[str, Any]:
    """A ``foxglove.SceneEntity``: every primitive list empty but those given (``lines=...``)."""
    entity: dict[str, Any] = {
        "timestamp": _time(stamp_ns),
        "frame_id": frame,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": frame_locked,
        "metadata": [{"key": k, "value": v} for k, v in metadata.items()],
    }
    for kind in _PRIMITIVES:
        entity[kind] = primitives.pop(kind, [])
    if primitives:
        raise TypeError(f"not a SceneEntity primitive: {', '.join(primitives)}")
    return entity


_PRIMITIVES = ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models")


def _dumps(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


# The views logged with every scan and pose are written from text templates: ``json.dumps`` of
# the nested dicts above costs several times more, and the recorder writes thousands a second.
# Each template gives the same JSON as ``_dumps`` of the dict (tests compare the two).


def _number(value: float) -> str:
    """A finite float as JSON (``ValueError`` otherwise, as ``json.dumps(allow_nan=False)``)."""
    if not math.isfinite(value):
        raise ValueError(f"out of range float value {value!r}")
    return repr(value)


def _time_text(ns: int) -> str:
    return f'{{"sec":{ns // 1_000_000_000},"nsec":{ns % 1_000_000_000}}}'


def _position_text(x: float, y: float) -> str:
    return f'{{"x":{_number(x)},"y":{_number(y)},"z":0.0}}'


def _orientation_text(theta: float) -> str:
    z, w = _number(math.sin(theta / 2)), _number(math.cos(theta / 2))
    return f'{{"x":0.0,"y":0.0,"z":{z},"w":{w}}}'


def _pose_text(x: float, y: float, theta: float) -> str:
    return f'{{"position":{_position_text(x, y)},"orientation":{_orientation_text(theta)}}}'


_WALL_COLOR_TEXT = _dumps(_WALL_COLOR).decode()
_OBSTACLE_COLOR_TEXT = _dumps(_OBSTACLE_COLOR).decode()
_LINE_HEAD = (
    f'{{"type":0,"pose":{_pose_text(0.0, 0.0, 0.0)},"thickness":{_number(_WALL_THICKNESS)},'
    '"scale_invariant":false,"points":['
)


_COORDINATES = re.compile(r'"coordinates"\s*:\s*\[')
_DECODER = json.JSONDecoder()


def _map_parts(payload: bytes) -> tuple[dict[str, Any], list[list[Any]]]:
    """A Map's fields (its coordinates left out) and its polygons' rings.

    The rings are parsed one at a time: ``json.loads`` of a map of real size holds the
    interpreter's lock for seconds (C code lets no other thread run), and the recorder shares
    the service's main process with the Zenoh callbacks. Falls back to ``json.loads`` for any
    layout this does not follow.
    """
    text = payload.decode("utf-8")
    found = _COORDINATES.search(text)
    if found is None:
        return _whole_map(text)
    start = found.end() - 1  # the coordinates' "["
    try:
        polygons, end = _rings_at(text, start)
        data = json.loads(text[:start] + "null" + text[end:])
    except (ValueError, IndexError, RecursionError):
        return _whole_map(text)
    if data.get("geometry", {}).get("type") == "Polygon" and len(polygons) == 1:
        return data, polygons
    if data.get("geometry", {}).get("type") == "MultiPolygon":
        return data, polygons
    return _whole_map(text)


def _whole_map(text: str) -> tuple[dict[str, Any], list[list[Any]]]:
    data = json.loads(text)
    geometry = data["geometry"]
    coords = geometry["coordinates"]
    return data, [coords] if geometry["type"] == "Polygon" else list(coords)


def _skip(text: str, i: int) -> int:
    while text[i] in " \t\r\n":
        i += 1
    return i


def _rings_at(text: str, i: int) -> tuple[list[list[Any]], int]:
    """The polygons of the coordinates array at ``i`` (a Polygon's is one polygon) and the
    index after it. A Polygon's array holds rings (arrays of positions), a MultiPolygon's
    arrays of rings: told apart by the depth of the first number."""
    j = _skip(text, i + 1)
    depth = 0
    k = j
    while text[k] == "[":
        depth += 1
        k = _skip(text, k + 1)
    multi = depth >= 3  # [[[x  (MultiPolygon: polygon, ring, position)
    polygons: list[list[Any]] = []
    current: list[Any] = []
    i = j
    while text[i] != "]":
        if multi:
            i = _skip(text, i + 1)  # into a polygon's "["
            current = []
            while text[i] != "]":
                ring, i = _DECODER.raw_decode(text, i)
                current.append(ring)
                i = _skip(text, i)
                if text[i] == ",":
                    i = _skip(text, i + 1)
            polygons.append(current)
            i = _skip(text, i + 1)
        else:
            ring, i = _DECODER.raw_decode(text, i)
            current.append(ring)
            i = _skip(text, i)
        if text[i] == ",":
            i = _skip(text, i + 1)
    if not multi:
        polygons.append(current)
    return polygons, i + 1


def _ring_text(ring: Any, color: str) -> str:
    """A ring as a LINE_STRIP (GeoJSON rings repeat their first point)."""
    xy = np.asarray(ring, dtype=np.float64)[:, :2]
    if not np.isfinite(xy).all():
        raise ValueError("non-finite coordinate in a map ring")
    points = ",".join(f'{{"x":{x!r},"y":{y!r},"z":0.0}}' for x, y in xy.tolist())
    return f'{_LINE_HEAD}{points}],"color":{color},"colors":[],"indices":[]}}'


def _split(topic: str, marker: str, depth: int) -> list[str] | None:
    """The last ``depth`` parts of ``.../{marker}/a[/b]``, or ``None``."""
    parts = topic.split("/")
    if len(parts) < depth + 2 or parts[-depth - 1] != marker:
        return None
    return parts[-depth:]


class FoxgloveConverter:
    """Makes the Foxglove messages of one logged message; remembers each map's frame."""

    def __init__(self) -> None:
        self._frames: dict[str, str] = {}

    def __call__(self, record: Record) -> list[Record]:
        """The Foxglove records of ``record`` (none for other schemas or bad payloads)."""
        handler = _HANDLERS.get(record.schema_name)
        if handler is None:
            return []
        try:
            return handler(self, record)
        except (ValueError, TypeError, KeyError, IndexError, AttributeError, RecursionError):
            # Inputs are validated before they are logged; a log from elsewhere may hold
            # anything, and a view is not worth failing a recording for.
            log.debug("no foxglove view of %s", record.topic, exc_info=True)
            return []

    def frame_of(self, map_id: str) -> str:
        """The frame of a map (``map`` until the map itself was seen)."""
        return self._frames.get(map_id, DEFAULT_FRAME)

    def note_frame(self, map_id: str, payload: bytes) -> None:
        """Learn a map's frame from its payload without converting it (a search of the bytes:
        milliseconds for a 10 MB map, whose conversion takes over a second)."""
        found = _FRAME_ID.search(payload)
        frame = json.loads(found.group(1)) if found else None
        self._frames[map_id] = str(frame or DEFAULT_FRAME)

    def _map(self, record: Record) -> list[Record]:
        parts = _split(record.topic, "maps", 1)
        if parts is None:
            return []
        map_id = parts[0]
        data, polygons = _map_parts(record.payload)
        frame = str(data.get("frame_id") or DEFAULT_FRAME)
        self._frames[map_id] = frame
        # Written from a template, splicing each ring's points: a map of real size has
        # hundreds of thousands of points, and a dict per point for json.dumps took seconds.
        lines = ",".join(
            _ring_text(ring, _WALL_COLOR_TEXT if i == 0 else _OBSTACLE_COLOR_TEXT)
            for rings in polygons
            for i, ring in enumerate(rings)
        )
        entity = scene_entity(
            record.log_time_ns,
            frame,
            f"map/{map_id}",
            {"map_id": map_id, "version": str(data.get("version", ""))},
            True,
        )
        update = {"deletions": [], "entities": [entity]}
        return [
            Record(
                f"/foxglove/maps/{map_id}",
                SCENE_UPDATE,
                _dumps(update).replace(b'"lines":[]', b'"lines":[' + lines.encode() + b"]", 1),
                record.log_time_ns,
                record.log_time_ns,
            )
        ]

    def _scan(self, record: Record) -> list[Record]:
        """A LaserScan's view, splicing its ranges' JSON text instead of parsing it.

        Formatting 360 floats costs about 40 times more than the rest of the view; the ranges
        are copied as the robot wrote them, with ``null`` (no return) as ``0``. Payloads whose
        ``ranges`` member is not one plain array of numbers and nulls take the parsing path.
        """
        payload = record.payload
        m = _RANGES.search(payload) if payload.count(b'"ranges"') == 1 else None
        end = payload.find(b"]", m.end()) if m else -1
        if m and end > 0:
            text = payload[m.end() : end].strip()
            if not text.translate(None, _NUMBERS_AND_NULLS):
                head: dict[str, Any] = json.loads(payload[: m.end()] + payload[end:])
                if head.get("ranges") == []:  # the spliced member is the one a parser sees
                    count = text.count(b",") + 1 if text else 0
                    return self._scan_view(record, head, (text.replace(b"null", b"0"), count))
        return self._scan_view(record, json.loads(payload))

    def _scan_view(
        self, record: Record, data: dict[str, Any], text: tuple[bytes, int] | None = None
    ) -> list[Record]:
        """The view of a parsed scan; ``text``: its ranges as JSON text and their count."""
        parts = _split(record.topic, "robots", 2)
        if parts is None:
            return []
        robot = parts[0]
        if text is None:
            ranges = [0.0 if r is None else float(r) for r in data["ranges"]]
            count = len(ranges)
        else:
            ranges, count = [], text[1]
        offset = data.get("sensor_offset") or {}
        start = float(data["angle_min"])
        end = start + (count - 1) * float(data["angle_increment"])
        pose = _pose_text(
            float(offset.get("x", 0.0)),
            float(offset.get("y", 0.0)),
            float(offset.get("theta", 0.0)),
        )
        head = (
            f'{{"timestamp":{_time_text(int(data["stamp_ns"]))},'
            f'"frame_id":{json.dumps(robot_frame(robot))},"pose":{pose},'
            f'"start_angle":{_number(start)},"end_angle":{_number(end)},"ranges":['
        ).encode()
        numbers = text[0] if text is not None else ",".join(map(_number, ranges)).encode()
        body = head + numbers + b'],"intensities":[]}'
        return [
            Record(
                f"/foxglove/robots/{robot}/scan",
                LASER_SCAN,
                body,
                record.log_time_ns,
                record.publish_time_ns,
            )
        ]

    def _located(self, record: Record) -> list[Record]:
        """A PoseEstimate or InitialPose: a pose in the map frame and the robot's transform."""
        data = json.loads(record.payload)
        parts = _split(record.topic, "robots", 2)
        if parts is None:
            return []
        robot, leaf = parts
        frame = json.dumps(self.frame_of(str(data["map_id"])))
        stamp = _time_text(int(data["stamp_ns"]))
        x, y, theta = float(data["x"]), float(data["y"]), float(data["theta"])
        position, orientation = _position_text(x, y), _orientation_text(theta)
        pose = (
            f'{{"timestamp":{stamp},"frame_id":{frame},'
            f'"pose":{{"position":{position},"orientation":{orientation}}}}}'
        )
        transform = (
            f'{{"timestamp":{stamp},"parent_frame_id":{frame},'
            f'"child_frame_id":{json.dumps(robot_frame(robot))},'
            f'"translation":{position},"rotation":{orientation}}}'
        )
        t, p = record.log_time_ns, record.publish_time_ns
        return [
            Record(f"/foxglove/robots/{robot}/{leaf}", POSE_IN_FRAME, pose.encode(), t, p),
            Record(TF_TOPIC, FRAME_TRANSFORM, transform.encode(), t, p),
        ]


_HANDLERS = {
    "rlutf.Map": FoxgloveConverter._map,
    "rlutf.LaserScan": FoxgloveConverter._scan,
    "rlutf.PoseEstimate": FoxgloveConverter._located,
    "rlutf.InitialPose": FoxgloveConverter._located,
}


def npm_schemas(prefix: Path) -> dict[str, Any]:
    """Foxglove's JSON Schemas of :data:`SCHEMA_NAMES` from ``@foxglove/schemas`` under ``prefix``.

    Args:
        prefix: where ``npm install --prefix PREFIX @foxglove/schemas`` was run.

    Raises:
        OSError: node is missing.
        subprocess.CalledProcessError: the package is not installed there.
    """
    module = prefix / "node_modules" / "@foxglove" / "schemas" / "jsonschema"
    script = (
        "const s = require(process.argv[1]); const out = {};"
        "for (const n of process.argv.slice(2)) out['foxglove.' + n] = s[n];"
        "process.stdout.write(JSON.stringify(out));"
    )
    short = [name.removeprefix("foxglove.") for name in SCHEMA_NAMES]
    done = subprocess.run(
        ["node", "-e", script, str(module), *short], check=True, capture_output=True, timeout=60
    )
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def embedded_dir() -> Path:
    """Where the embedded schema documents live in the source tree."""
    return Path(__file__).with_name("foxglove_schemas")


def main(argv: list[str] | None = None) -> int:
    """``python -m service.logs.foxglove DIR``: install the npm package and rewrite the schemas."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m service.logs.foxglove NPM_PREFIX_DIR", file=sys.stderr)
        return 2
    prefix = Path(args[0])
    subprocess.run(["npm", "install", "--prefix", str(prefix), "@foxglove/schemas"], check=True)
    for name, schema in npm_schemas(prefix).items():
        path = embedded_dir() / f"{name}.json"
        path.write_text(json.dumps(schema, indent=2) + "\n", encoding="utf-8")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
