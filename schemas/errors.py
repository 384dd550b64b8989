"""Exceptions of the wire-schema package.

Every error raised on purpose by :mod:`schemas` derives from :class:`SchemaError`, itself a
:class:`ValueError`, so a boundary (a Zenoh callback, replay, the CLI) catches one type and
puts ``str(err)`` into an ``invalid_message`` Event. Each subclass formats its own message
from structured attributes, which stay available to callers that want more than text.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

MAX_ISSUES_IN_MESSAGE = 3
"""How many field issues :class:`InvalidMessage` spells out before summarising the rest."""


class SchemaError(ValueError):
    """Base class of every error raised by :mod:`schemas`."""


class PayloadTooLarge(SchemaError):
    """A payload is over the size limit; raised before any parsing.

    Args:
        size: Payload size in bytes (UTF-8 bytes for text).
        limit: The limit it broke, in bytes.
    """

    def __init__(self, size: int, limit: int) -> None:
        self.size = size
        self.limit = limit
        super().__init__(f"payload too large: {size} bytes, limit {limit}")


class MalformedJson(SchemaError):
    """A payload is not a JSON document.

    Args:
        detail: What the parser found wrong and where, e.g.
            ``"expected value at line 1 column 7"``.
    """

    def __init__(self, detail: str) -> None:
        self.detail = detail
        super().__init__(f"malformed JSON: {detail}")


class InvalidUtf8(MalformedJson):
    """A payload is not UTF-8 text, which RFC 8259 requires of JSON exchanged between systems.

    Args:
        position: Byte offset of the first invalid byte.
        reason: The decoder's explanation, e.g. ``"invalid start byte"``.
    """

    def __init__(self, position: int, reason: str) -> None:
        self.position = position
        self.reason = reason
        super().__init__(f"invalid UTF-8 at byte {position}: {reason}")


@dataclass(frozen=True, slots=True)
class FieldIssue:
    """One thing wrong with one field of a decoded message.

    Attributes:
        path: Where in the document, e.g. ``"ranges[17]"`` or ``"geometry.coordinates[0]"``;
            ``"payload"`` for the document itself.
        message: What is wrong, e.g. ``"input should be a number or null"``.
        value: The offending input rendered as JSON and shortened, or ``None`` where there is
            no input to show (a missing field).
    """

    path: str
    message: str
    value: str | None = None

    def __str__(self) -> str:
        if self.value is None:
            return f"{self.path}: {self.message}"
        return f"{self.path}: {self.message}, got {self.value}"


class InvalidMessage(SchemaError):
    """A well-formed JSON document that breaks the message schema.

    The message lists the first :data:`MAX_ISSUES_IN_MESSAGE` issues, e.g.
    ``ranges[17]: input should be a number or null, got "abc"``.

    Args:
        model: Name of the message type, e.g. ``"LaserScan"``.
        issues: Every issue found, in document order; at least one.
    """

    def __init__(self, model: str, issues: Sequence[FieldIssue]) -> None:
        self.model = model
        self.issues = tuple(issues)
        shown = "; ".join(str(issue) for issue in self.issues[:MAX_ISSUES_IN_MESSAGE])
        hidden = len(self.issues) - MAX_ISSUES_IN_MESSAGE
        if hidden > 0:
            shown += f" (and {hidden} more)"
        super().__init__(shown or f"invalid {model}")


class EncodeError(SchemaError):
    """A message cannot be rendered as JSON, e.g. a non-finite number in a model built with
    ``model_construct`` (which skips validation).

    Args:
        model: Name of the message type.
        detail: What went wrong.
    """

    def __init__(self, model: str, detail: str) -> None:
        self.model = model
        self.detail = detail
        super().__init__(f"cannot encode {model}: {detail}")
