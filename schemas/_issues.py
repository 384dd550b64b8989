"""Turn pydantic validation errors into :class:`schemas.errors.FieldIssue` values.

Paths are written the way a JSON reader expects (``ranges[17]``, ``geometry.coordinates[0]``)
and messages in JSON terms (object, array, number) rather than Python ones (dictionary,
tuple, float), since robots and dashboards on the other side of the wire need not be Python.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any, Final

from pydantic_core import ErrorDetails

from schemas.errors import FieldIssue
from schemas.geometry import GEOMETRY_TYPES

MAX_VALUE_CHARS: Final = 40
"""Longest rendering of an offending value in a message; longer ones are cut with ``...``."""

ROOT_PATH: Final = "payload"
"""Path shown for an issue with the document as a whole."""

_MESSAGES: Final = {
    "missing": "field required",
    "model_type": "input should be an object",
    "model_attributes_type": "input should be an object",
    "dict_type": "input should be an object",
    "float_type": "input should be a number",
    "float_parsing": "input should be a number",
    "int_type": "input should be an integer",
    "int_parsing": "input should be an integer",
    "int_from_float": "input should be an integer",
    "string_type": "input should be a string",
    "list_type": "input should be an array",
    "tuple_type": "input should be an array",
    "finite_number": "input should be a finite number",
}


def format_path(loc: Iterable[int | str]) -> str:
    """Render a pydantic error location as a JSON path.

    Discriminated unions add the tag to the location (``geometry.Polygon.coordinates``);
    it names no member of the document, so it is left out.

    Args:
        loc: The error's ``loc``, e.g. ``("ranges", 17)``.

    Returns:
        E.g. ``"ranges[17]"``; :data:`ROOT_PATH` for an empty location.
    """
    path = ""
    previous: int | str | None = None
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        elif not (previous == "geometry" and part in GEOMETRY_TYPES):
            path += f".{part}" if path else part
        previous = part
    return path or ROOT_PATH


def format_value(value: Any) -> str:
    """Render an offending input as JSON, at most :data:`MAX_VALUE_CHARS` characters long.

    Args:
        value: The input as parsed from JSON (``nan`` and ``inf`` render as JSON5 tokens).

    Returns:
        E.g. ``'"abc"'``, ``'true'``, ``'NaN'``, ``'[1.0, 2.0, ...'``.
    """
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    if len(text) > MAX_VALUE_CHARS:
        text = text[: MAX_VALUE_CHARS - 3] + "..."
    return text


def _items(count: int) -> str:
    return f"{count} item" if count == 1 else f"{count} items"


def _is_echo(error: ErrorDetails) -> bool:
    """Tell a length error that only echoes failed items.

    pydantic-core counts a sequence's length after dropping the items that failed, so a bad
    position in a ring also reports the ring, its polygon and the polygon list as too short.
    The items' own errors say what is wrong; the echo would only mislead.
    """
    if error["type"] != "too_short":
        return False
    value = error["input"]
    ctx = error.get("ctx") or {}
    return isinstance(value, list | tuple) and len(value) >= ctx.get("min_length", 0)


def _message(error: ErrorDetails) -> str:
    kind = error["type"]
    ctx = error.get("ctx") or {}
    if kind in _MESSAGES:
        return _MESSAGES[kind]
    if kind == "too_short":
        return f"array should have at least {_items(ctx['min_length'])}, not {ctx['actual_length']}"
    if kind == "too_long":
        return f"array should have at most {_items(ctx['max_length'])}, not {ctx['actual_length']}"
    text = error["msg"]
    return text[:1].lower() + text[1:]


def issues_from_errors(errors: Iterable[ErrorDetails]) -> list[FieldIssue]:
    """Convert pydantic's ``ValidationError.errors()`` into field issues.

    Args:
        errors: Error details, in the order pydantic found them.

    Returns:
        One issue per error, less length errors that only echo failed items. A missing field
        shows no value: pydantic's input there is the enclosing object.
    """
    return [
        FieldIssue(
            path=format_path(error["loc"]),
            message=_message(error),
            value=None if error["type"] == "missing" else format_value(error["input"]),
        )
        for error in errors
        if not _is_echo(error)
    ]
