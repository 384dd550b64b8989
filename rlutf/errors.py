"""Exceptions of the algorithm library.

Every error raised on purpose by :mod:`rlutf` derives from :class:`RlutfError`, so callers at a
boundary (the service, the CLI) can catch one type and report the message, which names what is
wrong and where.
"""

from __future__ import annotations


class RlutfError(Exception):
    """Base class of every error raised by :mod:`rlutf`."""


class GeometryError(RlutfError, ValueError):
    """An input polygon or array has the wrong shape or is degenerate."""


class MapError(RlutfError, ValueError):
    """A map geometry is invalid: empty, self-intersecting, unclosed or non-finite."""


class ConfigError(RlutfError, ValueError):
    """A localizer configuration value is out of its allowed range."""
