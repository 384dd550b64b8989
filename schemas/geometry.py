"""GeoJSON map geometry (RFC 7946 Polygon and MultiPolygon), validated structurally.

A ring is an array of at least four ``[x, y]`` positions of finite numbers whose first and
last positions are equal. Whether the rings are simple, correctly nested and non-overlapping is
geometric validity, which :mod:`rlutf` checks when it loads the map; here only the shape of the
document is enforced, so a bad map is rejected with a path to the offending part.
"""

from __future__ import annotations

from typing import Annotated, Final, Literal

from pydantic import AfterValidator, Field
from pydantic_core import PydanticCustomError

from schemas._types import FiniteFloat, WireModel

MIN_RING_POSITIONS: Final = 4
"""A closed ring needs three distinct corners plus the repeated first one."""

GEOMETRY_TYPES: Final = ("Polygon", "MultiPolygon")
"""Values of the GeoJSON ``type`` member accepted for a map."""

Position = tuple[FiniteFloat, FiniteFloat]
"""An ``[x, y]`` pair in metres. GeoJSON's optional third (altitude) value is not accepted."""


def _check_closed(ring: tuple[Position, ...]) -> tuple[Position, ...]:
    if ring and ring[0] != ring[-1]:
        raise PydanticCustomError(
            "ring_not_closed",
            "ring is not closed: first position {first} differs from last {last}",
            {"first": list(ring[0]), "last": list(ring[-1])},
        )
    return ring


LinearRing = Annotated[
    tuple[Position, ...],
    Field(min_length=MIN_RING_POSITIONS),
    AfterValidator(_check_closed),
]
"""A closed ring of at least :data:`MIN_RING_POSITIONS` positions."""

PolygonCoordinates = Annotated[tuple[LinearRing, ...], Field(min_length=1)]
"""The exterior ring first, then any holes."""


class Polygon(WireModel):
    """A GeoJSON Polygon: free space inside the exterior ring, obstacles inside the holes."""

    type: Literal["Polygon"] = Field(description='Always "Polygon".')
    coordinates: PolygonCoordinates = Field(
        description="Rings of [x, y] positions in metres: the exterior first, then holes; "
        "each closed (first position repeated last) with at least 4 positions."
    )

    @property
    def polygons(self) -> tuple[tuple[tuple[Position, ...], ...], ...]:
        """The rings of each polygon; here exactly one polygon."""
        return (self.coordinates,)


class MultiPolygon(WireModel):
    """A GeoJSON MultiPolygon: several disjoint free-space areas on one map."""

    type: Literal["MultiPolygon"] = Field(description='Always "MultiPolygon".')
    coordinates: Annotated[tuple[PolygonCoordinates, ...], Field(min_length=1)] = Field(
        description="Polygons, each given as its rings (exterior first, then holes)."
    )

    @property
    def polygons(self) -> tuple[tuple[tuple[Position, ...], ...], ...]:
        """The rings of each polygon."""
        return self.coordinates


Geometry = Annotated[Polygon | MultiPolygon, Field(discriminator="type")]
"""A map geometry, told apart by its GeoJSON ``type``."""
