"""Schema names of the messages and their JSON Schema documents.

An MCAP log registers each channel's schema with encoding ``jsonschema``, the name from
:data:`SCHEMA_NAMES` and the document from :func:`json_schema` (WIRE.md, MCAP logs). The same
documents are checked in under ``schemas/jsonschema/`` by ``python -m schemas.generate``.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any, Final

from schemas._types import WireModel
from schemas.answers import RobotsAnswer, StoredVersion
from schemas.maphealth import MapHealth
from schemas.messages import (
    Event,
    Health,
    InitialPose,
    LaserScan,
    Map,
    Odometry,
    PoseEstimate,
    Relocalize,
)

JSON_SCHEMA_DIALECT: Final = "https://json-schema.org/draft/2020-12/schema"

SCHEMA_NAMES: Final[MappingProxyType[type[WireModel], str]] = MappingProxyType(
    {
        LaserScan: "rlutf.LaserScan",
        Odometry: "rlutf.Odometry",
        InitialPose: "rlutf.InitialPose",
        Relocalize: "rlutf.Relocalize",
        PoseEstimate: "rlutf.PoseEstimate",
        Map: "rlutf.Map",
        Event: "rlutf.Event",
        MapHealth: "rlutf.MapHealth",
        Health: "rlutf.Health",
        StoredVersion: "rlutf.StoredVersion",
        RobotsAnswer: "rlutf.RobotsAnswer",
    }
)
"""Schema name of every top-level message; all but the answers to queries (Health,
StoredVersion, RobotsAnswer) are logged to MCAP."""

MODELS_BY_SCHEMA_NAME: Final[MappingProxyType[str, type[WireModel]]] = MappingProxyType(
    {name: model for model, name in SCHEMA_NAMES.items()}
)
"""The inverse of :data:`SCHEMA_NAMES`, for readers of a log."""


def schema_name(model_cls: type[WireModel]) -> str:
    """Return the schema name of a top-level message type.

    Args:
        model_cls: A top-level message type, e.g. :class:`~schemas.messages.LaserScan`.

    Returns:
        E.g. ``"rlutf.LaserScan"``.

    Raises:
        KeyError: ``model_cls`` is not a top-level message.
    """
    return SCHEMA_NAMES[model_cls]


def _inline_refs(node: Any, defs: dict[str, Any]) -> Any:
    """Replace every ``$ref`` to a local definition by a copy of it (the models hold no cycles).

    Self-contained documents suit the simplest readers, as Foxglove's own schemas are.
    """
    if isinstance(node, list):
        return [_inline_refs(item, defs) for item in node]
    if not isinstance(node, dict):
        return node
    out: dict[str, Any] = {}
    ref = node.get("$ref")
    if isinstance(ref, str) and ref.startswith("#/$defs/"):
        out.update(_inline_refs(defs[ref.removeprefix("#/$defs/")], defs))
    for key, value in node.items():
        if key == "$ref":
            continue
        if key == "discriminator" and isinstance(value, dict):
            # The mapping points into $defs, which are gone; the property name still helps.
            out[key] = {k: v for k, v in value.items() if k != "mapping"}
        else:
            out[key] = _inline_refs(value, defs)
    return out


def json_schema(model_cls: type[WireModel]) -> dict[str, Any]:
    """Build the JSON Schema (draft 2020-12) of a top-level message, with no ``$ref``.

    It describes what :func:`schemas.decode` accepts, except what JSON Schema cannot say:
    numbers must be finite, map rings closed, ``angle_increment`` non-zero and ``range_max``
    above ``range_min``.

    Args:
        model_cls: A key of :data:`SCHEMA_NAMES`.

    Returns:
        The schema document, titled with the schema name.
    """
    name = schema_name(model_cls)
    raw = model_cls.model_json_schema(mode="validation")
    defs = raw.pop("$defs", {})
    schema: dict[str, Any] = _inline_refs(raw, defs)
    schema["$schema"] = JSON_SCHEMA_DIALECT
    schema["title"] = name
    return schema
