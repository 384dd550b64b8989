"""Field types shared by the wire messages: finite numbers, stamps, identifiers.

Scalars are strict (no ``"1.5"`` -> 1.5, no ``true`` -> 1; an integer is accepted where a
number is expected, as JSON does not tell them apart) and numbers must be finite. Containers
stay lax: at run time Python callers may pass lists (or numpy arrays) where a model stores
tuples, though type checkers, which see the tuple annotations, want tuples.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Final

from pydantic import AllowInfNan, BaseModel, ConfigDict, Field, GetCoreSchemaHandler, Strict
from pydantic_core import PydanticCustomError, core_schema

ID_PATTERN: Final = r"[A-Za-z0-9_-]{1,64}"
"""Robot ids and map ids (WIRE.md, Keys): 1 to 64 ASCII letters, digits, ``_`` or ``-``."""

_ID_REGEX: Final = re.compile(ID_PATTERN)

MAX_STAMP_NS: Final = 2**63 - 1
"""Largest stamp accepted: stamps are int64 nanoseconds, as in ROS 2 and the MCAP log."""


def valid_id(text: str) -> bool:
    """Tell whether ``text`` may be used as a robot id or map id in a key.

    Args:
        text: Candidate id, e.g. the ``{robot}`` segment of a key.

    Returns:
        True if the whole of ``text`` matches :data:`ID_PATTERN`.
    """
    return isinstance(text, str) and _ID_REGEX.fullmatch(text) is not None


class WireModel(BaseModel):
    """Base of every wire message and of the models nested in one.

    Frozen (messages are values), unknown fields ignored (WIRE.md: add optional fields
    freely), non-finite numbers rejected.
    """

    model_config = ConfigDict(frozen=True, extra="ignore", allow_inf_nan=False)


class _CustomError:
    """Replace every validation error of the annotated type by one message.

    Used where pydantic's own wording would mislead a non-Python reader, e.g. a range that
    may be a number or ``null``. The check itself stays in pydantic-core, so it costs nothing.
    """

    def __init__(self, error_type: str, message: str) -> None:
        self.error_type = error_type
        self.message = message

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        return core_schema.custom_error_schema(
            handler(source), custom_error_type=self.error_type, custom_error_message=self.message
        )


FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
"""A finite JSON number (an integer is accepted and stored as float)."""

NonNegativeFloat = Annotated[FiniteFloat, Field(ge=0.0)]
"""A finite JSON number >= 0."""

PositiveFloat = Annotated[FiniteFloat, Field(gt=0.0)]
"""A finite JSON number > 0."""

UnitFloat = Annotated[FiniteFloat, Field(ge=0.0, le=1.0)]
"""A finite JSON number in [0, 1]."""

NonNegativeInt = Annotated[int, Strict(), Field(ge=0)]
"""A JSON integer >= 0 (``3.0`` is not an integer)."""

StampNs = Annotated[int, Strict(), Field(ge=0, le=MAX_STAMP_NS)]
"""Integer nanoseconds since the Unix epoch, in int64 range."""

NumberOrNull = Annotated[
    FiniteFloat | None, _CustomError("number_or_null", "input should be a number or null")
]
"""A finite JSON number or ``null``."""

Identifier = Annotated[str, Strict(), Field(min_length=1, max_length=64, pattern=f"^{ID_PATTERN}$")]
"""A robot id or map id, see :data:`ID_PATTERN`."""

NonEmptyStr = Annotated[str, Strict(), Field(min_length=1)]
"""A string of at least one character."""

Text = Annotated[str, Strict()]
"""Any string, possibly empty."""


def check_finite_json(value: Any) -> Any:
    """Reject NaN and infinities anywhere inside a free-form JSON value.

    Args:
        value: A value validated as ``JsonValue``.

    Returns:
        ``value`` unchanged.

    Raises:
        PydanticCustomError: A float inside is NaN or infinite.
    """
    if isinstance(value, float) and not math.isfinite(value):
        raise PydanticCustomError("finite_number", "input should be a finite number")
    if isinstance(value, dict):
        for item in value.values():
            check_finite_json(item)
    elif isinstance(value, list):
        for item in value:
            check_finite_json(item)
    return value
