"""Exceptions of the map import and build tools.

Every error raised on purpose by :mod:`service.maps.mapimport` derives from :class:`MapImportError`,
so the CLI catches one type and prints ``str(err)``, which names the file, key or value at
fault. Errors of the libraries underneath (PIL, PyYAML, shapely, :mod:`rlutf`) are wrapped at
the boundary with ``raise ... from err``.
"""

from __future__ import annotations


class MapImportError(Exception):
    """Base class of every error raised by :mod:`service.maps.mapimport`."""


class MapFileError(MapImportError):
    """A file is missing or cannot be read or decoded (image, YAML, log)."""


class MapYamlError(MapImportError):
    """A map_server YAML document is malformed, lacks a key or has a wrong value."""


class EmptyMapError(MapImportError):
    """The grid (or the part of it that was selected) holds no free space."""


class GridTooLargeError(MapImportError):
    """A grid to build would take more memory than a build allows (its cells at the resolution
    given)."""


class ComponentError(MapImportError):
    """The free-space component the user asked for does not exist."""


class CarmenError(MapImportError):
    """A CARMEN log line cannot be parsed."""
