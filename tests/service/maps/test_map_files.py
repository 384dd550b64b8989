"""``rlutf map put FILE``: the files people have (a Map message, GeoJSON as a geometry, a Feature
or a FeatureCollection, as geojson.io and QGIS export it) become the same Map, and a file that
is none of them is named with what it is and what to do."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas import Map, decode
from service.maps.client import map_message_from_file

ROOM = [[[0.0, 0.0], [6.0, 0.0], [6.0, 4.0], [0.0, 4.0], [0.0, 0.0]]]
ANNEX = [[[8.0, 0.0], [10.0, 0.0], [10.0, 2.0], [8.0, 2.0], [8.0, 0.0]]]


def _file(tmp_path: Path, name: str, data: object) -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


def _feature(kind: str, coordinates: object) -> dict[str, object]:
    geometry = {"type": kind, "coordinates": coordinates}
    return {"type": "Feature", "properties": {"name": "x"}, "geometry": geometry}


def test_a_feature_collection_is_the_map_of_its_polygons(tmp_path: Path) -> None:
    bare = map_message_from_file(
        _file(tmp_path, "bare.json", {"type": "Polygon", "coordinates": ROOM}), "site", 1
    )
    one = {"type": "FeatureCollection", "features": [_feature("Polygon", ROOM)]}
    assert map_message_from_file(_file(tmp_path, "one.geojson", one), "site", 1) == bare
    two = {
        "type": "FeatureCollection",
        "features": [_feature("Polygon", ROOM), _feature("MultiPolygon", [ANNEX])],
    }
    both = decode(Map, map_message_from_file(_file(tmp_path, "two.geojson", two), "site", 1))
    assert both.geometry.type == "MultiPolygon" and len(both.geometry.coordinates) == 2
    assert both.map_id == "site" and both.version == 1


@pytest.mark.parametrize(
    ("data", "said"),
    [
        ({"type": "FeatureCollection", "features": []}, "no features"),
        (
            {"type": "FeatureCollection", "features": [_feature("Polygon", ROOM), {"a": 1}]},
            "feature 2 of 2 is a feature without geometry",
        ),
        (
            {"type": "FeatureCollection", "features": [_feature("LineString", ROOM[0])]},
            "feature 1 of 1 is a LineString",
        ),
        (
            {
                "type": "FeatureCollection",
                "features": [_feature("Polygon", ROOM), _feature("Polygon", ROOM)],
            },
            "invalid map",  # two polygons on top of each other
        ),
    ],
)
def test_a_collection_that_is_no_map_is_refused_with_why(
    tmp_path: Path, data: object, said: str
) -> None:
    with pytest.raises(ValueError, match=said):
        map_message_from_file(_file(tmp_path, "c.geojson", data), "site", 1)


def test_a_file_that_is_no_json_is_named_with_what_to_do(tmp_path: Path) -> None:
    binary = tmp_path / "site.pgm"
    binary.write_bytes(b"P5\n\xff\xfe\x00")
    with pytest.raises(ValueError, match=r"site.pgm: not UTF-8 text.*rlutf map import"):
        map_message_from_file(binary, None, None)
    yaml = tmp_path / "site.yaml"
    yaml.write_text("image: site.pgm\nresolution: 0.05\n")
    with pytest.raises(ValueError, match=r"site.yaml: malformed JSON.*rlutf map import .* --put"):
        map_message_from_file(yaml, None, None)
    other = tmp_path / "notes.json"
    other.write_text("{not json")
    with pytest.raises(ValueError, match=r"notes.json: malformed JSON: [^;]*$"):
        map_message_from_file(other, None, None)


def test_map_show_draws_a_feature_collection(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli.main import main

    two = {
        "type": "FeatureCollection",
        "features": [_feature("Polygon", ROOM), _feature("Polygon", ANNEX)],
    }
    png = tmp_path / "two.png"
    assert main(["map", "show", str(_file(tmp_path, "two.geojson", two)), "--out", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    line = {"type": "FeatureCollection", "features": [_feature("LineString", ROOM[0])]}
    assert main(["map", "show", str(_file(tmp_path, "l.geojson", line)), "--out", str(png)]) == 2
    assert "feature 1 of 1 is a LineString" in capsys.readouterr().err


def test_a_json_file_with_a_byte_order_mark_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A GeoJSON saved by Windows Notepad begins with a UTF-8 byte order mark, which JSON lets a
    reader ignore: ``rlutf map put`` and ``map show`` refused it ("malformed JSON: Unexpected
    UTF-8 BOM (decode using utf-8-sig)")."""
    from service.cli.main import main

    plain = _file(tmp_path, "plain.json", {"type": "Polygon", "coordinates": ROOM})
    marked = tmp_path / "marked.json"
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    assert map_message_from_file(marked, "site", 1) == map_message_from_file(plain, "site", 1)
    png = tmp_path / "marked.png"
    assert main(["map", "show", str(marked), "--out", str(png)]) == 0, capsys.readouterr().err
