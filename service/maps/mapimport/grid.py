"""ROS map_server occupancy grids: YAML metadata, image decoding, saving,.

Loading follows Nav2's ``map_io`` exactly. A pixel's shade is the mean of its red, green and
blue values scaled to ``[0, 1]`` (in ``trinary`` mode the alpha channel, if any, is averaged in
too); its occupancy is ``p = 1 - shade``, or ``p = shade`` when ``negate`` is set.

- ``trinary`` (default): occupied if ``p > occupied_thresh``, free if ``p < free_thresh``,
  else unknown.
- ``scale``: as trinary, except that a pixel that is not fully opaque is unknown.
- ``raw``: the pixel value itself (0..255, ``negate`` not applied) is the occupancy in percent;
  values over 100 are unknown. Free and occupied then follow the same thresholds on
  ``value / 100``.

Image row 0 is the top of the map (largest y). :class:`OccupancyGrid` stores rows bottom-up,
as ``nav_msgs/OccupancyGrid`` does, so ``data[row, col]`` is the cell whose lower-left corner
is ``(col, row) * resolution`` in the grid frame, which ``origin`` ``[x, y, yaw]`` places in
the map frame (rotation by ``yaw`` about the lower-left corner of the lower-left pixel).
Unknown cells count as walls downstream: only free cells are free space.

Parsers take text or bytes; only :func:`load_grid` and :func:`save_grid` touch files.
:func:`service.maps.mapimport.raymarch.march_rays` casts rays on a grid for comparison.
"""

from __future__ import annotations

import io
import math
import re
import reprlib
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal, cast

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from PIL import Image, UnidentifiedImageError

from service.infile import read_regular
from service.maps.mapimport.errors import MapFileError, MapYamlError
from service.yamlfile import YamlTooLarge, load_yaml, problem, where

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Mode = Literal["trinary", "scale", "raw"]

MODES: tuple[Mode, ...] = ("trinary", "scale", "raw")
REQUIRED_KEYS = ("image", "resolution", "origin", "occupied_thresh", "free_thresh")
#: The cell sizes a floor map may have, metres: a tenth of a millimetre to a kilometre. Past
#: them, a typo or another unit (1e-300 m crashed the import; 1e300 m spanned more than a float).
MIN_RESOLUTION: Final = 1e-4
MAX_RESOLUTION: Final = 1e3
#: Farthest origin from 0, metres (UTM coordinates are within it): past it a cell is below the
#: float's precision.
MAX_ORIGIN: Final = 1e8
#: The most of a map's YAML that is read (map_server's are a few hundred bytes).
MAX_YAML_BYTES: Final = 1 << 20
#: The most of a map's image that is read: Pillow refuses more than about 179 million pixels
#: (:data:`PIL.Image.MAX_IMAGE_PIXELS` twice), at most 4 bytes each, before it decodes them.
MAX_IMAGE_BYTES: Final = 1 << 30

#: Pixel values map_saver writes for free, occupied and unknown cells (trinary).
SAVE_FREE, SAVE_OCCUPIED, SAVE_UNKNOWN = 254, 0, 205


@dataclass(frozen=True)
class MapMetadata:
    """The contents of a map_server YAML file.

    Attributes:
        image: image file name as written (absolute, or relative to the YAML's folder).
        resolution: metres per cell.
        origin: ``(x, y, yaw)`` of the lower-left corner of the lower-left pixel, metres and
            radians.
        negate: whether white means occupied.
        occupied_thresh: occupancy above which a cell is occupied.
        free_thresh: occupancy below which a cell is free.
        mode: ``trinary``, ``scale`` or ``raw``.
    """

    image: str
    resolution: float
    origin: tuple[float, float, float]
    negate: bool = False
    occupied_thresh: float = 0.65
    free_thresh: float = 0.25
    mode: Mode = "trinary"


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """An occupancy grid with its placement in the map frame.

    Attributes:
        data: ``(rows, cols)`` int8, row 0 at the bottom; ``nav_msgs/OccupancyGrid`` values:
            0..100 occupancy percent, -1 unknown.
        free: ``(rows, cols)`` cells that are free space.
        occupied: ``(rows, cols)`` cells that are occupied; the rest are unknown.
        resolution: metres per cell.
        origin: ``(x, y, yaw)`` of the grid's lower-left corner in the map frame.
    """

    data: NDArray[np.int8]
    free: BoolArray
    occupied: BoolArray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.data.ndim != 2 or self.free.shape != self.data.shape:
            raise ValueError("data and free must be 2-D arrays of one shape")
        if self.occupied.shape != self.data.shape:
            raise ValueError("occupied must have the shape of data")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"resolution must be positive, got {self.resolution}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return (int(self.data.shape[0]), int(self.data.shape[1]))

    @property
    def free_cells(self) -> int:
        """Number of free cells."""
        return int(np.count_nonzero(self.free))

    @property
    def cell_area(self) -> float:
        """Area of one cell, square metres."""
        return self.resolution * self.resolution

    @property
    def affine(self) -> tuple[float, float, float, float, float, float]:
        """Grid frame (metres) to map frame, as shapely's ``[a, b, d, e, xoff, yoff]``."""
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        return (c, -s, s, c, x0, y0)

    def to_world(self, local: ArrayLike) -> FloatArray:
        """Map-frame coordinates of ``(K, 2)`` grid-frame points (metres)."""
        p = np.asarray(local, dtype=np.float64).reshape(-1, 2)
        a, b, d, e, xo, yo = self.affine
        return np.column_stack([a * p[:, 0] + b * p[:, 1] + xo, d * p[:, 0] + e * p[:, 1] + yo])

    def to_local(self, world: ArrayLike) -> FloatArray:
        """Grid-frame coordinates (metres) of ``(K, 2)`` map-frame points."""
        p = np.asarray(world, dtype=np.float64).reshape(-1, 2)
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = p[:, 0] - x0, p[:, 1] - y0
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy])

    def cell_centres(self, rows: ArrayLike, cols: ArrayLike) -> FloatArray:
        """Map-frame centres ``(K, 2)`` of the cells ``(rows[k], cols[k])``."""
        r = np.asarray(rows, dtype=np.float64).reshape(-1)
        c = np.asarray(cols, dtype=np.float64).reshape(-1)
        return self.to_world(np.column_stack([c + 0.5, r + 0.5]) * self.resolution)


#: How a value of the YAML is shown in an error: a few items and levels. A document's aliases
#: can nest a list in itself nine times over (YAML's "billion laughs", a few hundred bytes): its
#: full repr took minutes and gigabytes.
_BRIEF = reprlib.Repr()
_BRIEF.maxlevel, _BRIEF.maxlist, _BRIEF.maxdict, _BRIEF.maxstring = 2, 4, 4, 60
_BRIEF.maxother = 60


def _brief(value: object) -> str:
    return _BRIEF.repr(value)


def _finite(value: object) -> float | None:
    """``value`` as a finite float, or ``None``. A string that reads as a number counts:
    map_server's yaml-cpp reads YAML 1.2, where ``5e-2`` is a number, and PyYAML's YAML 1.1
    gives it as a string (its floats need a dot: ``5.0e-2``)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, str):
        try:
            value = float(value.strip())
        except ValueError:
            return None
    if not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _number(doc: dict[str, Any], key: str) -> float:
    value = _finite(doc[key])
    if value is None:
        raise MapYamlError(f"map YAML: '{key}' must be a finite number, got {_brief(doc[key])}")
    return value


def parse_map_yaml(text: str | bytes) -> MapMetadata:
    """Parse a map_server YAML document.

    Args:
        text: the YAML document.

    Returns:
        The metadata; ``negate`` defaults to false and ``mode`` to ``trinary``.

    Raises:
        MapYamlError: not YAML, not a mapping, a required key missing (all are named), or a
            value of the wrong type or out of range.
    """
    try:
        doc = load_yaml(text)
    except (yaml.YAMLError, YamlTooLarge) as err:
        raise MapYamlError(
            f"map YAML{where(err)}: cannot parse it ({problem(err)}); fix the file: a "
            "map_server YAML is 'key: value' lines (image, resolution, origin, occupied_thresh, "
            "free_thresh)"
        ) from err
    if not isinstance(doc, dict):
        raise MapYamlError(f"map YAML: expected a mapping of keys, got {type(doc).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in doc]
    if missing:
        names = ", ".join(f"'{k}'" for k in missing)
        raise MapYamlError(f"map YAML: missing required key(s) {names}")
    image = doc["image"]
    if not isinstance(image, str) or not image.strip():
        raise MapYamlError(f"map YAML: 'image' must be a file name, got {_brief(image)}")
    resolution = _number(doc, "resolution")
    if resolution <= 0:
        raise MapYamlError(f"map YAML: 'resolution' must be positive, got {resolution}")
    given = doc["origin"]
    values = [_finite(v) for v in given] if isinstance(given, list) else []
    origin = [v for v in values if v is not None]
    if len(values) != 3 or len(origin) != 3:
        raise MapYamlError(f"map YAML: 'origin' must be [x, y, yaw] numbers, got {_brief(given)}")
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise MapYamlError(
            f"map YAML: 'resolution' must be between {MIN_RESOLUTION:g} and {MAX_RESOLUTION:g} "
            f"m per cell, got {resolution:g} (the size of a cell, in metres)"
        )
    if max(abs(origin[0]), abs(origin[1])) > MAX_ORIGIN:
        raise MapYamlError(
            f"map YAML: 'origin' x and y must be within {MAX_ORIGIN:g} m of 0, got "
            f"{_brief(given)} (the position of the lower-left cell, in metres)"
        )
    occ, free = _number(doc, "occupied_thresh"), _number(doc, "free_thresh")
    for key, value in (("occupied_thresh", occ), ("free_thresh", free)):
        if not 0.0 <= value <= 1.0:
            raise MapYamlError(f"map YAML: '{key}' must be in [0, 1], got {value}")
    if free > occ:
        raise MapYamlError(f"map YAML: 'free_thresh' {free} is above 'occupied_thresh' {occ}")
    negate = doc.get("negate", 0)
    if negate not in (0, 1) or not isinstance(negate, int | bool):
        raise MapYamlError(f"map YAML: 'negate' must be 0 or 1, got {_brief(negate)}")
    mode = doc.get("mode", "trinary")
    if not isinstance(mode, str) or mode.strip().lower() not in MODES:
        raise MapYamlError(
            f"map YAML: 'mode' must be one of {', '.join(MODES)}, got {_brief(mode)}"
        )
    return MapMetadata(
        image=image.strip(),
        resolution=resolution,
        origin=(origin[0], origin[1], origin[2]),
        negate=bool(negate),
        occupied_thresh=occ,
        free_thresh=free,
        mode=cast(Mode, mode.strip().lower()),
    )


#: Image rows converted at once: the float temporaries of a large map are a band's, not the
#: whole image's (a 4000 x 6000 map took 1.1 GB to load in float64 at once).
BAND_ROWS = 256


def _decode(image: bytes, name: str) -> tuple[NDArray[Any], NDArray[Any] | None, float]:
    """Colour channels ``(H, W, C)`` and alpha ``(H, W)`` (or None) as the image holds them,
    and the value of full scale (``[0, 1]`` after dividing by it)."""
    try:
        with warnings.catch_warnings():
            # Pillow warns past MAX_IMAGE_PIXELS (89 M) and refuses past twice that: a site's
            # map of 100 M cells (a 500 m square at 5 cm) is taken without a warning.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            img: Image.Image = Image.open(io.BytesIO(image))
            img.load()
    except Image.DecompressionBombError as err:
        limit = 2 * (Image.MAX_IMAGE_PIXELS or 0)
        found = re.search(r"\((\d+) pixels\)", str(err))
        size = f"{int(found[1]):,} pixels" if found else str(err)
        raise MapFileError(
            f"{name}: the image has {size}, more than map import takes ({limit:,}): crop it, "
            "or scale it down and raise the YAML's resolution to match"
        ) from err
    except UnidentifiedImageError as err:  # its message names a BytesIO object, not the file
        raise MapFileError(
            f"{name}: not an image map import reads (PGM, PNG, BMP, TIFF, ...: what map_server "
            "writes)"
        ) from err
    except (OSError, ValueError) as err:
        raise MapFileError(f"{name}: cannot decode the image: {err}") from err
    if img.mode == "P":
        img = img.convert("RGBA" if "transparency" in img.info else "RGB")
    elif img.mode in ("PA", "RGBa", "RGBX"):
        img = img.convert("RGBA" if img.mode != "RGBX" else "RGB")
    elif img.mode in ("La",):
        img = img.convert("LA")
    elif img.mode == "1":
        img = img.convert("L")
    elif img.mode in ("CMYK", "YCbCr", "LAB", "HSV"):
        img = img.convert("RGB")
    if img.mode not in ("L", "LA", "RGB", "RGBA") and not img.mode.startswith("I"):
        raise MapFileError(f"{name}: unsupported image mode {img.mode!r}")
    scale = 255.0 if img.mode in ("L", "LA", "RGB", "RGBA") else 65535.0
    arr = np.asarray(img)
    if arr.ndim == 2:
        return arr[:, :, None], None, scale
    if img.mode in ("LA", "RGBA"):
        return arr[:, :, :-1], arr[:, :, -1], scale
    return arr, None, scale


def _classify(
    colour: FloatArray, alpha: FloatArray | None, meta: MapMetadata
) -> tuple[FloatArray, BoolArray, BoolArray]:
    """Occupancy values, free and occupied cells of image rows scaled to ``[0, 1]``."""
    shade = colour.mean(axis=2)
    if meta.mode == "trinary" and alpha is not None:
        n = colour.shape[2]
        shade = (shade * n + alpha) / (n + 1)
    if meta.mode == "raw":
        percent = np.rint(shade * 255.0)
        known = percent <= 100.0
        occ = np.where(known, percent / 100.0, np.nan)
        data = np.where(known, percent, -1.0)
    else:
        occ = shade if meta.negate else 1.0 - shade
        known = np.ones(occ.shape, dtype=bool)
        if meta.mode == "scale" and alpha is not None:
            known = alpha >= 1.0
        span = max(meta.occupied_thresh - meta.free_thresh, 1e-12)
        between = np.rint((occ - meta.free_thresh) / span * 100.0) if meta.mode == "scale" else -1
        data = np.where(
            occ > meta.occupied_thresh, 100.0, np.where(occ < meta.free_thresh, 0.0, between)
        )
        data = np.where(known, data, -1.0)
    return data, known & (occ < meta.free_thresh), known & (occ > meta.occupied_thresh)


def grid_from_image(image: bytes, meta: MapMetadata, *, name: str = "image") -> OccupancyGrid:
    """Decode a map image with its metadata, following Nav2's map_server.

    Args:
        image: the PGM, PNG or other Pillow-readable image file's bytes.
        meta: the YAML metadata.
        name: how to call the image in error messages (its path).

    Returns:
        The grid, rows bottom-up.

    Raises:
        MapFileError: the bytes are not a readable image.
    """
    colour, alpha, scale = _decode(image, name)
    rows, cols = colour.shape[:2]
    if rows == 0 or cols == 0:
        raise MapFileError(f"{name}: the image is empty")
    data = np.empty((rows, cols), dtype=np.int8)
    free = np.empty((rows, cols), dtype=bool)
    occupied = np.empty((rows, cols), dtype=bool)
    for r0 in range(0, rows, BAND_ROWS):  # in float64, as map_server, a band at a time
        band = slice(r0, min(rows, r0 + BAND_ROWS))
        a = None if alpha is None else alpha[band].astype(np.float64) / scale
        d, f, o = _classify(colour[band].astype(np.float64) / scale, a, meta)
        data[band], free[band], occupied[band] = d.astype(np.int8), f, o
    return OccupancyGrid(
        data=np.ascontiguousarray(data[::-1]),
        free=np.ascontiguousarray(free[::-1]),
        occupied=np.ascontiguousarray(occupied[::-1]),
        resolution=meta.resolution,
        origin=meta.origin,
    )


#: How the images a map_server map names start (PNG, TIFF, JPEG, GIF; PGM and PPM below): given
#: in place of the YAML, one is said to be an image rather than "cannot parse" as YAML.
_IMAGE_MAGIC = (b"\x89PNG\r\n", b"II*\x00", b"MM\x00*", b"\xff\xd8\xff", b"GIF87a", b"GIF89a")


def _an_image(data: bytes) -> bool:
    """Whether ``data`` starts as an image a map_server YAML would name."""
    return data.startswith(_IMAGE_MAGIC) or re.match(rb"P[2356]\s", data) is not None


def load_grid(yaml_path: str | Path) -> OccupancyGrid:
    """Load a map_server map from its YAML file and the image it names.

    Raises:
        MapFileError: the YAML or image file is missing or unreadable.
        MapYamlError: the YAML is malformed or lacks a key.
    """
    path = Path(yaml_path)
    try:
        text = read_regular(path, MAX_YAML_BYTES)
    except OSError as err:
        raise MapFileError(f"map YAML '{path}': cannot read: {err.strerror or err}") from err
    if _an_image(text):
        raise MapYamlError(
            f"{path}: an image, not the map's YAML: give the YAML file that names it in its "
            "'image' key (map_server and map_saver write the two side by side)"
        )
    try:
        meta = parse_map_yaml(text)
    except MapYamlError as err:
        raise MapYamlError(f"{path}: {err}") from err
    image_path = Path(meta.image)
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    try:
        image = read_regular(image_path, MAX_IMAGE_BYTES)
    except OSError as err:
        raise MapFileError(
            f"image file '{image_path}' (named by 'image' in '{path}'): "
            f"cannot read: {err.strerror or err}"
        ) from err
    return grid_from_image(image, meta, name=str(image_path))


def encode_pgm(grid: OccupancyGrid) -> bytes:
    """The grid as a binary PGM the way map_saver writes it (free 254, occupied 0, unknown 205)."""
    pixels = np.full(grid.shape, SAVE_UNKNOWN, dtype=np.uint8)
    pixels[grid.free] = SAVE_FREE
    pixels[grid.occupied] = SAVE_OCCUPIED
    rows, cols = grid.shape
    return f"P5\n{cols} {rows}\n255\n".encode("ascii") + pixels[::-1].tobytes()


def encode_map_yaml(grid: OccupancyGrid, image: str) -> str:
    """The YAML document for :func:`encode_pgm`'s image (thresholds 0.65 and 0.196)."""
    doc = {
        "image": image,
        "mode": "trinary",
        "resolution": grid.resolution,
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": 0.65,
        # ROS 1 map_saver's value: 205 (unknown) is p = 0.19608, just above it. With Nav2's
        # 0.25 the unknown cells would load back as free.
        "free_thresh": 0.196,
    }
    return str(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def save_grid(grid: OccupancyGrid, yaml_path: str | Path) -> Path:
    """Write the grid as ``<stem>.pgm`` beside ``yaml_path`` and the YAML; return the image path.

    Raises:
        MapFileError: a file cannot be written.
    """
    path = Path(yaml_path)
    image_path = path.with_suffix(".pgm")
    try:
        image_path.write_bytes(encode_pgm(grid))
        path.write_text(encode_map_yaml(grid, image_path.name), encoding="utf-8")
    except OSError as err:
        raise MapFileError(f"cannot write map '{path}': {err.strerror or err}") from err
    return image_path
