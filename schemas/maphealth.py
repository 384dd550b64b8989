"""The MapHealth message (WIRE.md v1.2): where the fleet's scans disagree with a map.

Robots see the world; where it no longer matches the map (a rack moved in, a wall taken down,
a door blocked), every robot that passes sees the same disagreement. A MapHealth lists the
places where it persisted: ``added`` (something the map lacks; a Polygon or MultiPolygon around
it) and ``removed`` (map walls that beams pass through; a LineString or MultiLineString along
them). It never edits the map: an operator decides.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from schemas._types import Identifier, NonNegativeInt, StampNs, UnitFloat, WireModel
from schemas.geometry import MultiPolygon, Polygon, Position

LinePositions = Annotated[tuple[Position, ...], Field(min_length=2)]
"""At least two ``[x, y]`` positions, metres."""


class LineString(WireModel):
    """A GeoJSON LineString."""

    type: Literal["LineString"] = Field(description='Always "LineString".')
    coordinates: LinePositions = Field(description="[x, y] positions in metres, at least two.")


class MultiLineString(WireModel):
    """A GeoJSON MultiLineString."""

    type: Literal["MultiLineString"] = Field(description='Always "MultiLineString".')
    coordinates: Annotated[tuple[LinePositions, ...], Field(min_length=1)] = Field(
        description="Lines, each at least two [x, y] positions in metres."
    )


ChangeGeometry = Annotated[
    Polygon | MultiPolygon | LineString | MultiLineString, Field(discriminator="type")
]
"""Where a change is: an area (added) or wall lines (removed)."""


class MapChange(WireModel):
    """One place where the world and the map disagree."""

    kind: Literal["added", "removed"] = Field(
        description="added: returns consistently short of the map (something the map lacks); "
        "removed: map walls that beams consistently pass through."
    )
    geometry: ChangeGeometry = Field(
        description="added: a Polygon or MultiPolygon around it; removed: a LineString or "
        "MultiLineString along the missing walls; metres, map frame."
    )
    evidence: NonNegativeInt = Field(description="Returns that showed it.")
    robots: NonNegativeInt = Field(description="Distinct robots that saw it.")
    first_ns: StampNs = Field(description="Stamp of the first scan that showed it.")
    last_ns: StampNs = Field(description="Stamp of the last scan that showed it.")
    confidence: UnitFloat = Field(description="0 to 1.")


class MapHealth(WireModel):
    """What the fleet's scans say about one version of a map."""

    map_id: Identifier = Field(description="The map.")
    version: NonNegativeInt = Field(description="The map version the evidence is about.")
    stamp_ns: StampNs = Field(description="Stamp of the newest scan counted.")
    since_ns: StampNs = Field(description="Stamp of the first scan counted on this version.")
    scans: NonNegativeInt = Field(description="Scans counted (at poses that fit well).")
    robots: NonNegativeInt = Field(description="Distinct robots whose scans were counted.")
    changes: tuple[MapChange, ...] = Field(
        default=(), description="The places where the disagreement persisted, added first."
    )
