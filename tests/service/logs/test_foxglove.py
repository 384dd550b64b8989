"""Foxglove views: valid against Foxglove's published JSON Schemas, embedded schemas current.

The schemas come from the npm package ``@foxglove/schemas``, installed once into a cache folder
(``RLUTF_NPM_CACHE`` or ``~/.cache/rlutf-tests/npm``). Tests skip only where npm is missing.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcaplog_fixtures import read_all, simulated_inputs

from schemas import Map, PoseEstimate, encode
from service.logs.foxglove import (
    FRAME_TRANSFORM,
    LASER_SCAN,
    POSE_IN_FRAME,
    SCENE_UPDATE,
    SCHEMA_NAMES,
    TF_TOPIC,
    FoxgloveConverter,
    embedded_dir,
    npm_schemas,
)
from service.logs.mcapfile import Record, schema_data
from service.logs.mcaplog import McapRecorder
from service.logs.replay import replay
from service.logs.salvage import recover

jsonschema = pytest.importorskip("jsonschema", reason="python jsonschema is not installed")


NPM_PACKAGES = ("@foxglove/schemas", "@mcap/core", "@mcap/support")

# Reads a file with Foxglove's own MCAP library (indexed reader, CRCs checked).
MCAP_CHECK = """
const [prefix, file] = process.argv.slice(1);
const { McapIndexedReader } = require(prefix + "/node_modules/@mcap/core");
const { loadDecompressHandlers } = require(prefix + "/node_modules/@mcap/support");
(async () => {
  const decompressHandlers = await loadDecompressHandlers();
  const buf = require("fs").readFileSync(file);
  const readable = {
    size: async () => BigInt(buf.length),
    read: async (offset, size) => buf.subarray(Number(offset), Number(offset + size)),
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  let messages = 0;
  for await (const _ of reader.readMessages({ validateCrcs: true })) messages++;
  const schemas = [...reader.schemasById.values()].map((s) => s.encoding + " " + s.name);
  console.log(JSON.stringify({ messages, schemas }));
})().catch((e) => { console.error(String(e)); process.exit(1); });
"""


@pytest.fixture(scope="session")
def npm_prefix() -> Path:
    if shutil.which("npm") is None or shutil.which("node") is None:
        pytest.skip("npm/node not installed: cannot fetch @foxglove/schemas and @mcap/core")
    prefix = Path(os.environ.get("RLUTF_NPM_CACHE", Path.home() / ".cache" / "rlutf-tests" / "npm"))
    if not all((prefix / "node_modules" / p).is_dir() for p in NPM_PACKAGES):
        prefix.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["npm", "install", "--prefix", str(prefix), "--no-audit", "--no-fund", *NPM_PACKAGES],
            check=True,
            capture_output=True,
            timeout=300,
        )
    return prefix


@pytest.fixture(scope="session")
def foxglove_schemas(npm_prefix: Path) -> dict[str, Any]:
    return npm_schemas(npm_prefix)


def _foxglove_reads(npm_prefix: Path, path: Path) -> dict[str, Any]:
    done = subprocess.run(
        ["node", "-e", MCAP_CHECK, str(npm_prefix), str(path)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def _validate(schema: dict[str, Any], payload: bytes) -> None:
    jsonschema.validate(json.loads(payload), schema)


def test_embedded_schemas_equal_the_npm_package(foxglove_schemas: dict[str, Any]) -> None:
    assert set(foxglove_schemas) == set(SCHEMA_NAMES)
    for name, schema in foxglove_schemas.items():
        embedded = json.loads((embedded_dir() / f"{name}.json").read_text())
        assert embedded == schema, f"{name} is stale: run python -m service.logs.foxglove DIR"
        assert json.loads(schema_data(name) or b"") == schema


def test_views_of_every_message_validate(foxglove_schemas: dict[str, Any]) -> None:
    conv = FoxgloveConverter()
    inputs = simulated_inputs(("r1",), steps=2)
    pose = PoseEstimate(
        stamp_ns=inputs[-1].publish_time_ns,
        robot_id="r1",
        map_id="m1",
        x=1.5,
        y=2.0,
        theta=-3.0,
        status="tracking",
        discrepancy=0.01,
        iterations=0,
    )
    records = [*inputs, Record("rlutf/robots/r1/pose", "rlutf.PoseEstimate", encode(pose), 9, 9)]
    seen: set[str] = set()
    for rec in records:
        for view in conv(rec):
            _validate(foxglove_schemas[view.schema_name], view.payload)
            seen.add(view.schema_name)
    assert seen == set(SCHEMA_NAMES)


def test_view_contents() -> None:
    conv = FoxgloveConverter()
    geometry = {
        "type": "MultiPolygon",
        "coordinates": [
            [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]], [[1, 1], [2, 1], [2, 2], [1, 2], [1, 1]]],
            [[[5, 0], [6, 0], [6, 1], [5, 0]]],
        ],
    }
    m = Map(map_id="hall", version=2, frame_id="site", geometry=geometry)
    (scene,) = conv(Record("x/maps/hall", "rlutf.Map", encode(m), 5, 5))
    assert scene.topic == "/foxglove/maps/hall" and scene.schema_name == SCENE_UPDATE
    entity = json.loads(scene.payload)["entities"][0]
    assert entity["frame_id"] == "site" and len(entity["lines"]) == 3
    assert entity["lines"][1]["points"][0] == {"x": 1.0, "y": 1.0, "z": 0.0}
    pose = PoseEstimate(
        stamp_ns=3_000_000_001,
        robot_id="r7",
        map_id="hall",
        x=1.0,
        y=2.0,
        theta=math.pi / 2,
        status="corrected",
        discrepancy=0.0,
        iterations=2,
    )
    located, tf = conv(Record("x/robots/r7/pose", "rlutf.PoseEstimate", encode(pose), 7, 6))
    assert (located.topic, located.schema_name) == ("/foxglove/robots/r7/pose", POSE_IN_FRAME)
    body = json.loads(located.payload)
    assert body["frame_id"] == "site" and body["timestamp"] == {"sec": 3, "nsec": 1}
    q = body["pose"]["orientation"]
    assert q["z"] == pytest.approx(math.sqrt(0.5)) and q["w"] == pytest.approx(math.sqrt(0.5))
    assert (tf.topic, tf.schema_name) == (TF_TOPIC, FRAME_TRANSFORM)
    t = json.loads(tf.payload)
    assert (t["parent_frame_id"], t["child_frame_id"]) == ("site", "r7/base_link")
    assert (tf.log_time_ns, tf.publish_time_ns) == (7, 6)
    scan = {
        "stamp_ns": 1,
        "angle_min": -1.0,
        "angle_increment": 0.5,
        "range_min": 0.1,
        "range_max": 5.0,
        "ranges": [1.0, None, 2.0],
        "sensor_offset": {"x": 0.2, "y": 0.0, "theta": 0.0},
    }
    (view,) = conv(Record("x/robots/r7/scan", "rlutf.LaserScan", json.dumps(scan).encode(), 1, 1))
    body = json.loads(view.payload)
    assert view.schema_name == LASER_SCAN and body["frame_id"] == "r7/base_link"
    assert body["ranges"] == [1.0, 0.0, 2.0] and body["end_angle"] == 0.0
    assert body["pose"]["position"]["x"] == 0.2
    assert conv(Record("x/robots/r7/odom", "rlutf.Odometry", b"{}", 1, 1)) == []
    assert conv(Record("x/robots/r7/scan", "rlutf.LaserScan", b"garbage", 1, 1)) == []


def test_recorded_log_carries_views_with_npm_schemas(
    tmp_path: Path, foxglove_schemas: dict[str, Any], npm_prefix: Path
) -> None:
    rec = McapRecorder(tmp_path, foxglove=True)
    for r in simulated_inputs(steps=3):
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    rec.close()
    views = read_all(rec.files[0], SCHEMA_NAMES)
    assert {v.topic for v in views} >= {
        "/foxglove/maps/m1",
        "/foxglove/robots/r1/scan",
        "/foxglove/robots/r2/initialpose",
        TF_TOPIC,
    }
    for v in views:
        _validate(foxglove_schemas[v.schema_name], v.payload)
    with open(rec.files[0], "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    logged = {s.name: json.loads(s.data) for s in summary.schemas.values()}
    for name in SCHEMA_NAMES:
        assert logged[name] == foxglove_schemas[name]
    # Foxglove's MCAP library reads the recorded, the replayed and a recovered log
    replay([rec.files[0]], tmp_path / "replayed.mcap")
    cut = tmp_path / "cut.mcap.part"
    cut.write_bytes(rec.files[0].read_bytes()[: rec.files[0].stat().st_size * 2 // 3])
    recover(cut, tmp_path / "recovered.mcap")
    for path in (rec.files[0], tmp_path / "replayed.mcap", tmp_path / "recovered.mcap"):
        seen = _foxglove_reads(npm_prefix, path)
        assert seen["messages"] == len(read_all(path)) > 0
        assert "jsonschema foxglove.LaserScan" in seen["schemas"]


@pytest.mark.parametrize(
    "scan, indent",
    [
        ({"ranges": [1.0, None, 2.5e-1, None]}, None),
        ({"ranges": [1.0, None, 2.0]}, 2),  # newlines and spaces inside the array
        ({"ranges": []}, None),
        ({"ranges": [3.0], "frame_id": "ranges"}, None),  # "ranges" twice in the text
        ({"frame_id": "lidar", "ranges": [1, 2, None]}, None),  # integers, member not last
    ],
)
def test_scan_view_from_text_equals_parsed_view(scan: dict[str, Any], indent: int | None) -> None:
    """The spliced view of a scan (its ranges copied as text) equals the one built by parsing."""
    body = {"stamp_ns": 5, "angle_min": 0.0, "angle_increment": 0.25, **scan}
    payload = json.dumps(body, indent=indent).encode()
    record = Record("x/robots/r1/scan", "rlutf.LaserScan", payload, 1, 1)
    conv = FoxgloveConverter()
    (fast,) = conv(record)
    (parsed,) = conv._scan_view(record, json.loads(payload))
    expected = json.loads(parsed.payload)
    assert json.loads(fast.payload) == expected
    assert expected["ranges"] == [0.0 if r is None else float(r) for r in body["ranges"]]
    assert expected["end_angle"] == 0.25 * (len(body["ranges"]) - 1)


@pytest.mark.parametrize("theta", [0.0, 1e-17, -math.pi, 2.5, 1e300])
def test_pose_views_equal_their_dict_form(theta: float) -> None:
    """The text templates give exactly the JSON of the nested dicts they stand for."""
    x, y, stamp = -1.5e-7, 123456.789, 1_700_000_000_123_456_789
    record = Record(
        "p/robots/r/pose",
        "rlutf.PoseEstimate",
        json.dumps({"stamp_ns": stamp, "map_id": "m", "x": x, "y": y, "theta": theta}).encode(),
        3,
        2,
    )
    located, tf = FoxgloveConverter()(record)
    time_ = {"sec": stamp // 10**9, "nsec": stamp % 10**9}
    position = {"x": x, "y": y, "z": 0.0}
    orientation = {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)}
    assert json.loads(located.payload) == {
        "timestamp": time_,
        "frame_id": "map",
        "pose": {"position": position, "orientation": orientation},
    }
    assert json.loads(tf.payload) == {
        "timestamp": time_,
        "parent_frame_id": "map",
        "child_frame_id": "r/base_link",
        "translation": position,
        "rotation": orientation,
    }


def test_views_of_non_finite_numbers_are_skipped() -> None:
    """A log from elsewhere may hold numbers JSON cannot carry: no view, no failure."""
    bad = b'{"stamp_ns": 1, "map_id": "m", "x": 1e999, "y": 0, "theta": 0}'
    assert FoxgloveConverter()(Record("p/robots/r/pose", "rlutf.PoseEstimate", bad, 1, 1)) == []


@pytest.mark.parametrize(
    "geometry",
    [
        {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 3], [0, 0]]]},
        {
            "coordinates": [
                [[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 0.0]],
                [[1.0, 1.0], [1.5, 1.0], [1.5, 1.5], [1.0, 1.0]],
            ],
            "type": "Polygon",
        },
        {
            "type": "MultiPolygon",
            "coordinates": [
                [[[0, 0], [1, 0], [1, 1], [0, 0]]],
                [
                    [[2, 2], [3, 2], [3, 3], [2, 2]],
                    [[2.2, 2.1], [2.3, 2.1], [2.3, 2.2], [2.2, 2.1]],
                ],
            ],
        },
    ],
)
@pytest.mark.parametrize("indent", [None, 2])
def test_a_maps_rings_parsed_one_by_one_equal_the_whole_parse(
    geometry: dict[str, Any], indent: int | None
) -> None:
    """The recorder parses a map's rings one at a time (a whole parse of a big map holds the
    interpreter's lock for seconds); the result is the same whatever the layout."""
    from service.logs.foxglove import _map_parts, _whole_map

    doc = {"frame_id": "coordinates", "map_id": "m", "version": 1, "geometry": geometry}
    text = json.dumps(doc, indent=indent)
    fields, polygons = _map_parts(text.encode())
    whole_fields, whole_polygons = _whole_map(text)
    assert polygons == whole_polygons
    assert fields["frame_id"] == whole_fields["frame_id"] == "coordinates"
    assert fields["geometry"]["type"] == geometry["type"]


def test_a_map_frame_is_learned_without_converting_the_map() -> None:
    """The live view converts a map only for a client that watches it; the robots drawn on it
    still need its frame."""
    from service.logs.foxglove import FoxgloveConverter

    conv = FoxgloveConverter()
    assert conv.frame_of("site") == "map"
    conv.note_frame("site", b'{"map_id":"site","version":2,"frame_id":"site\\"s","geometry":{}}')
    assert conv.frame_of("site") == 'site"s'
    conv.note_frame("site", b'{"map_id":"site","version":3,"frame_id":null,"geometry":{}}')
    assert conv.frame_of("site") == "map"
