"""Schema names, JSON Schema documents and the checked-in schema files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import schemas
from schemas import (
    MODELS_BY_SCHEMA_NAME,
    SCHEMA_NAMES,
    Event,
    Health,
    InitialPose,
    LaserScan,
    Map,
    Odometry,
    PoseEstimate,
    Relocalize,
    RobotsAnswer,
    StoredVersion,
    json_schema,
    schema_name,
)
from schemas.generate import SCHEMA_DIR, main, render_schemas, stale_files, write_schemas

MCAP_SCHEMA_NAMES = {
    "rlutf.LaserScan",
    "rlutf.Odometry",
    "rlutf.InitialPose",
    "rlutf.Relocalize",
    "rlutf.PoseEstimate",
    "rlutf.Map",
    "rlutf.Event",
    "rlutf.MapHealth",  # v1.2
}
#: Answered on a query, never logged.
ANSWER_SCHEMA_NAMES = {"rlutf.Health", "rlutf.StoredVersion", "rlutf.RobotsAnswer"}


def _walk(node: Any) -> list[Any]:
    found = [node]
    if isinstance(node, dict):
        for value in node.values():
            found += _walk(value)
    elif isinstance(node, list):
        for value in node:
            found += _walk(value)
    return found


def test_schema_names_are_the_wire_md_ones() -> None:
    assert set(SCHEMA_NAMES.values()) == MCAP_SCHEMA_NAMES | ANSWER_SCHEMA_NAMES
    assert schema_name(LaserScan) == "rlutf.LaserScan"
    models = (LaserScan, Odometry, InitialPose, Relocalize, PoseEstimate, Map, Event, Health)
    for model in (*models, schemas.MapHealth, StoredVersion, RobotsAnswer):
        assert SCHEMA_NAMES[model] == f"rlutf.{model.__name__}"
        assert MODELS_BY_SCHEMA_NAME[SCHEMA_NAMES[model]] is model
    with pytest.raises(KeyError):
        schema_name(schemas.SensorOffset)


@pytest.mark.parametrize("model", list(SCHEMA_NAMES))
def test_json_schema_is_self_contained(model: type[schemas.WireModel]) -> None:
    schema = json_schema(model)
    assert schema["title"] == SCHEMA_NAMES[model]
    assert schema["type"] == "object"
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert "$defs" not in schema
    refs = [node for node in _walk(schema) if isinstance(node, dict) and "$ref" in node]
    assert refs == []
    assert set(schema["properties"]) == set(model.model_fields)
    required = {name for name, field in model.model_fields.items() if field.is_required()}
    assert set(schema.get("required", [])) == required


def test_json_schema_carries_the_constraints() -> None:
    scan = json_schema(LaserScan)
    assert scan["properties"]["ranges"]["maxItems"] == schemas.MAX_BEAMS
    assert scan["properties"]["sensor_offset"]["properties"]["x"]["type"] == "number"
    assert scan["properties"]["stamp_ns"]["type"] == "integer"
    pose = json_schema(PoseEstimate)
    assert pose["properties"]["status"]["enum"] == ["tracking", "corrected", "lost"]
    assert pose["properties"]["robot_id"]["pattern"] == "^[A-Za-z0-9_-]{1,64}$"
    geometry = json_schema(Map)["properties"]["geometry"]
    kinds = [option["properties"]["type"]["const"] for option in geometry["oneOf"]]
    assert kinds == ["Polygon", "MultiPolygon"]
    assert geometry["discriminator"] == {"propertyName": "type"}


def test_checked_in_schema_files_match_the_models() -> None:
    # Fails when a model changes without `python -m schemas.generate` being run.
    assert stale_files(SCHEMA_DIR) == []
    for model, name in SCHEMA_NAMES.items():
        text = (SCHEMA_DIR / f"{name}.json").read_text(encoding="utf-8")
        assert json.loads(text) == json_schema(model)
        assert text.endswith("}\n")
        assert text == json.dumps(json_schema(model), indent=2, sort_keys=True) + "\n"


def test_check_reports_every_kind_of_drift(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--check", "--dir", str(tmp_path)]) == 1
    assert capsys.readouterr().err.count("out of date") == len(SCHEMA_NAMES)

    assert main(["--dir", str(tmp_path)]) == 0
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(render_schemas())
    assert main(["--check", "--dir", str(tmp_path)]) == 0

    edited = tmp_path / "rlutf.Odometry.json"
    edited.write_text(edited.read_text().replace('"x"', '"x_m"'))
    (tmp_path / "rlutf.Removed.json").write_text("{}\n")
    (tmp_path / "rlutf.Event.json").unlink()
    capsys.readouterr()
    assert main(["--check", "--dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    for name in ("rlutf.Odometry.json", "rlutf.Removed.json", "rlutf.Event.json"):
        assert name in err
    assert "rlutf.LaserScan.json" not in err

    assert write_schemas(tmp_path) == [
        "rlutf.Event.json",
        "rlutf.Odometry.json",
        "rlutf.Removed.json",
    ]
    assert not (tmp_path / "rlutf.Removed.json").exists()
    assert stale_files(tmp_path) == []
    assert write_schemas(tmp_path) == []


def test_module_runs_as_a_script() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "schemas.generate", "--check"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
