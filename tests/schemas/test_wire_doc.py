"""docs/wire.md, the wire contract in the repository: its examples are valid messages, and
every key and schema name it lists is the one the code uses."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from schemas import SCHEMA_NAMES, StoredVersion, decode
from service.keys import Keys
from service.live.robots import robots_key

WIRE = Path(__file__).resolve().parents[2] / "docs" / "wire.md"
TEXT = WIRE.read_text(encoding="utf-8")
MODELS = {name.removeprefix("rlutf."): model for model, name in SCHEMA_NAMES.items()}


def examples() -> list[tuple[str, str]]:
    """``(heading, JSON text)`` of each example, with the ``###`` heading it stands under."""
    out = []
    for m in re.finditer(r"^### (\w+).*?(?=^### |^## |\Z)", TEXT, flags=re.M | re.S):
        blocks = re.findall(r"^```json\n(.*?)^```", m.group(0), flags=re.M | re.S)
        out += [(m.group(1), text) for text in blocks]
    return out


def test_every_example_is_a_valid_message() -> None:
    found = examples()
    names = [name for name, _ in found]
    assert set(MODELS) - {"Health"} <= set(names), names
    for name, text in found:
        data = json.loads(text)
        if name in MODELS:
            assert decode(MODELS[name], text).model_dump(exclude_unset=True).keys() <= data.keys()


@pytest.mark.parametrize("schema", sorted(SCHEMA_NAMES.values()))
def test_every_schema_name_is_listed(schema: str) -> None:
    if schema == "rlutf.Health":  # answered on a query, never logged
        return
    assert f"`{schema}`" in TEXT


def test_keys_are_the_ones_the_service_uses() -> None:
    keys = Keys("{prefix}")
    for key in (
        keys.robot("{robot}", "scan"),
        keys.robot("{robot}", "odom"),
        keys.robot("{robot}", "initialpose"),
        keys.robot("{robot}", "relocalize"),
        keys.robot("{robot}", "pose"),
        keys.robot("{robot}", "events"),
        keys.map("{map_id}"),
        keys.map_version("{map_id}"),
        keys.health("{instance}"),
        robots_key("{prefix}", "{instance}"),
    ):
        assert f"`{key}`" in TEXT, key
    assert "version 1.2" in TEXT and "`rlutf.run`" in TEXT and "`rlutf.config`" in TEXT


def test_the_stored_version_example_is_what_the_store_answers() -> None:
    (text,) = [text for name, text in examples() if name == "StoredVersion"]
    assert StoredVersion.model_validate_json(text).model_dump().keys() == json.loads(text).keys()


def test_the_health_section_says_how_to_tell_a_hosts_sum_from_its_processes() -> None:
    """A get on ``{prefix}/service/*/health`` hears a multi-process ``rlutf serve``'s processes
    and its host, whose Health adds theirs up: a dashboard that sums the answers counts every
    robot twice unless the contract says which answer is the sum (the host's, marked
    ``extra.host``, service/live/host.py) and that the host declares no token."""
    section = re.search(r"^### Health\n(.*?)(?=^### )", TEXT, flags=re.M | re.S)
    assert section is not None
    text = " ".join(section.group(1).split())
    assert "`extra.host`" in text and "no token" in text and "-p0" in text
    host = (Path(__file__).resolve().parents[2] / "service" / "live" / "host.py").read_text()
    assert '"host": True' in host and '"by_process"' in host


def test_the_maphealth_section_says_when_a_get_gets_no_reply() -> None:
    """``MapHealthEngine.answer`` is ``None`` (no reply to a get) for a map with nothing counted
    on its current version: a tool polling the key must be able to tell that from the doc."""
    from service.keys import Keys as _Keys
    from service.maphealth import MapHealthEngine

    assert MapHealthEngine(_Keys()).answer("m1") is None
    section = re.search(r"^### MapHealth.*?\n(.*?)(?=^## )", TEXT, flags=re.M | re.S)
    assert section is not None
    text = " ".join(section.group(1).split())
    assert "gets no reply" in text and "first scan counted" in text
