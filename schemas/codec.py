"""Decode wire payloads into validated messages and encode messages into payloads.

``decode`` is the one entry point for bytes coming off the bus or out of a log: it checks the
size before parsing, parses and validates in one pass in pydantic-core, and turns every failure
into a :class:`~schemas.errors.SchemaError` whose message names the field and the value.
``encode`` writes compact, deterministic UTF-8 JSON.
"""

from __future__ import annotations

import json
from typing import Any, Final, TypeAlias, TypeVar

from pydantic import BaseModel, ValidationError

from schemas._issues import issues_from_errors
from schemas._types import WireModel
from schemas.errors import (
    EncodeError,
    InvalidMessage,
    InvalidUtf8,
    MalformedJson,
    PayloadTooLarge,
)

DEFAULT_MAX_BYTES: Final = 1_000_000
"""Default payload size limit of :func:`decode`, bytes."""

M = TypeVar("M", bound=WireModel)

Payload: TypeAlias = bytes | bytearray | memoryview | str
"""What :func:`decode` accepts: UTF-8 bytes in any buffer, or already decoded text."""


def _payload_size(payload: Payload, max_bytes: int) -> int:
    """Size in bytes, or a lower bound of it that is already over ``max_bytes``."""
    if isinstance(payload, memoryview):
        return payload.nbytes
    if not isinstance(payload, str):
        return len(payload)
    if len(payload) > max_bytes or payload.isascii():
        return len(payload)  # UTF-8 takes at least one byte per character
    return len(payload.encode("utf-8", "surrogatepass"))


def decode(model_cls: type[M], payload: Payload, *, max_bytes: int = DEFAULT_MAX_BYTES) -> M:
    """Parse and validate one message.

    Args:
        model_cls: The expected message type, e.g. :class:`~schemas.messages.LaserScan`.
        payload: The JSON document, as UTF-8 bytes or text.
        max_bytes: Size limit in bytes, checked before anything is parsed.

    Returns:
        The validated, frozen message.

    Raises:
        PayloadTooLarge: The payload is over ``max_bytes``.
        InvalidUtf8: The bytes are not UTF-8.
        MalformedJson: The text is not JSON.
        InvalidMessage: The document breaks the schema (missing field, wrong type, non-finite
            number, constraint); the message names each field and value.
    """
    size = _payload_size(payload, max_bytes)
    if size > max_bytes:
        raise PayloadTooLarge(size, max_bytes)
    data: str | bytes | bytearray = bytes(payload) if isinstance(payload, memoryview) else payload
    try:
        return model_cls.model_validate_json(data)
    except ValidationError as err:
        raise _decode_error(model_cls, data, err) from err


def _decode_error(
    model_cls: type[BaseModel], data: str | bytes | bytearray, err: ValidationError
) -> MalformedJson | InvalidMessage:
    errors = err.errors(include_url=False)
    if any(error["type"] == "string_unicode" and not error["loc"] for error in errors):
        return MalformedJson("text holds a lone surrogate, which is not Unicode")
    syntax = next((error for error in errors if error["type"] == "json_invalid"), None)
    if syntax is None:
        return InvalidMessage(model_cls.__name__, issues_from_errors(errors))
    if not isinstance(data, str):
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as bad:
            return InvalidUtf8(bad.start, bad.reason)
    ctx = syntax.get("ctx") or {}
    return MalformedJson(str(ctx.get("error", syntax["msg"])))


def _sorted_keys(value: Any) -> Any:
    """Copy free-form JSON with every object's keys sorted, so equal values give equal bytes."""
    if isinstance(value, dict):
        return {key: _sorted_keys(value[key]) for key in sorted(value)}
    if isinstance(value, list | tuple):
        return [_sorted_keys(item) for item in value]
    return value


def to_jsonable(message: BaseModel) -> dict[str, Any]:
    """Convert a message into plain JSON-ready Python values, fields in declaration order.

    An optional field whose default is ``None`` is left out while it is ``None``: a decoder
    reads absence and ``null`` alike, and WIRE.md calls such fields optional, e.g.
    ``PoseEstimate.covariance``. Nested messages, alone or in a sequence, become dicts;
    free-form dicts get sorted keys.

    Args:
        message: Any model of this package.

    Returns:
        A dict ready for :func:`json.dumps`.
    """
    out: dict[str, Any] = {}
    for name, field in type(message).model_fields.items():
        value = getattr(message, name)
        if value is None and field.default is None:
            continue
        if isinstance(value, BaseModel):
            value = to_jsonable(value)
        elif isinstance(value, tuple) and value and isinstance(value[0], BaseModel):
            value = [to_jsonable(item) for item in value]
        elif isinstance(value, dict):
            value = _sorted_keys(value)
        out[name] = value
    return out


def encode(message: WireModel) -> bytes:
    """Render a message as compact UTF-8 JSON.

    Deterministic: equal messages give identical bytes. Floats are written with Python's
    shortest round-trip ``repr``, so decoding gives back the same floats bit for bit.

    Args:
        message: The message to send or record.

    Returns:
        The payload.

    Raises:
        EncodeError: A value cannot be written as JSON: a non-finite number in a message that
            skipped validation, or a string holding a lone surrogate.
    """
    obj = to_jsonable(message)
    try:
        text = json.dumps(obj, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as err:
        raise EncodeError(type(message).__name__, str(err)) from err
    try:
        return text.encode("utf-8")
    except UnicodeEncodeError as err:  # a lone surrogate, which no JSON decoder accepts either
        raise EncodeError(type(message).__name__, str(err)) from err
