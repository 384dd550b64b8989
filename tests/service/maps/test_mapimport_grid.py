"""map_server YAML and image loading, saving, and the grid ray marcher."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.cli.main import main
from service.maps.mapimport import (
    MapFileError,
    MapImportError,
    MapMetadata,
    MapYamlError,
    OccupancyGrid,
    encode_pgm,
    grid_from_image,
    load_grid,
    march_rays,
    parse_map_yaml,
    save_grid,
)

YAML = """\
image: room.pgm
resolution: 0.1
origin: [1.0, -2.0, 0.0]
negate: 0
occupied_thresh: 0.65
free_thresh: 0.25
"""


def pgm(pixels: np.ndarray) -> bytes:
    rows, cols = pixels.shape
    return f"P5\n{cols} {rows}\n255\n".encode() + pixels.astype(np.uint8).tobytes()


def png(pixels: np.ndarray, mode: str) -> bytes:
    out = io.BytesIO()
    Image.fromarray(pixels.astype(np.uint8), mode=mode).save(out, format="PNG")
    return out.getvalue()


def meta(**kw: object) -> MapMetadata:
    base: dict[str, object] = {"image": "x.pgm", "resolution": 0.1, "origin": (0.0, 0.0, 0.0)}
    base.update(kw)
    return MapMetadata(**base)  # type: ignore[arg-type]


def test_parse_yaml_reads_keys_and_defaults() -> None:
    m = parse_map_yaml(YAML.replace("negate: 0\n", ""))
    assert m == MapMetadata("room.pgm", 0.1, (1.0, -2.0, 0.0), False, 0.65, 0.25, "trinary")
    assert parse_map_yaml(YAML + "mode: Scale\n").mode == "scale"
    assert parse_map_yaml(YAML.encode()).negate is False


def test_parse_yaml_reads_numbers_as_map_server_does() -> None:
    """map_server's yaml-cpp reads YAML 1.2, where ``5e-2`` is a number; PyYAML (YAML 1.1) gives
    it as a string, which was refused ("'resolution' must be a finite number, got '5e-2'")."""
    m = parse_map_yaml(
        YAML.replace("resolution: 0.1", "resolution: 1e-1")
        .replace("origin: [1.0, -2.0, 0.0]", "origin: [1e0, '-2', 0]")
        .replace("free_thresh: 0.25", "free_thresh: 25e-2")
        .replace("occupied_thresh: 0.65", "occupied_thresh: 65E-2")
    )
    assert m == MapMetadata("room.pgm", 0.1, (1.0, -2.0, 0.0), False, 0.65, 0.25, "trinary")
    for text, words in (
        ("resolution: nan", "'resolution' must be a finite number, got 'nan'"),
        ("resolution: 1e999", "'resolution' must be a finite number"),
        ("resolution: '5 cm'", "'resolution' must be a finite number, got '5 cm'"),
        ("resolution: -5e-2", "'resolution' must be positive, got -0.05"),
    ):
        with pytest.raises(MapYamlError, match=words):
            parse_map_yaml(YAML.replace("resolution: 0.1", text))
    with pytest.raises(MapYamlError, match="'origin' must be"):
        parse_map_yaml(YAML.replace("origin: [1.0, -2.0, 0.0]", "origin: [1e0, x, 0]"))


def test_parse_yaml_names_every_missing_key() -> None:
    text = "image: a.pgm\nnegate: 0\nfree_thresh: 0.2\n"
    with pytest.raises(MapYamlError) as err:
        parse_map_yaml(text)
    for key in ("resolution", "origin", "occupied_thresh"):
        assert f"'{key}'" in str(err.value)
    assert "'free_thresh'" not in str(err.value)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (("origin: [1.0, -2.0, 0.0]", "origin: [1.0, 2.0]"), "'origin'"),
        (("resolution: 0.1", "resolution: -0.1"), "'resolution' must be positive"),
        (("resolution: 0.1", "resolution: fine"), "'resolution' must be a finite number"),
        (("negate: 0", "negate: 2"), "'negate'"),
        (("free_thresh: 0.25", "free_thresh: 0.9"), "'free_thresh' 0.9 is above"),
        (("occupied_thresh: 0.65", "occupied_thresh: 1.5"), "'occupied_thresh' must be in"),
        (("image: room.pgm", "image: 3"), "'image' must be a file name"),
        (("negate: 0", "mode: fancy"), "'mode' must be one of"),
    ],
)
def test_parse_yaml_rejects_bad_values(edit: tuple[str, str], words: str) -> None:
    with pytest.raises(MapYamlError, match=words):
        parse_map_yaml(YAML.replace(*edit))


def test_parse_yaml_rejects_non_mappings_and_syntax_errors() -> None:
    with pytest.raises(MapYamlError, match="expected a mapping"):
        parse_map_yaml("- 1\n- 2\n")
    with pytest.raises(MapYamlError, match="cannot parse"):
        parse_map_yaml("image: [unclosed\n")


def test_trinary_thresholds_follow_map_server() -> None:
    # Row 0 of the image is the top of the map.
    pixels = np.array([[254, 205, 0], [128, 254, 254]])
    depot = grid_from_image(pgm(pixels), meta(free_thresh=0.25))
    # 205 is p = 50/255 = 0.196: free under 0.25, unknown under 0.196 (tb3_sandbox).
    assert depot.free.tolist() == [[False, True, True], [True, True, False]]
    assert depot.occupied.tolist() == [[False, False, False], [False, False, True]]
    assert depot.data.tolist() == [[-1, 0, 0], [0, 0, 100]]
    tb3 = grid_from_image(pgm(pixels), meta(free_thresh=0.196))
    assert tb3.free.tolist() == [[False, True, True], [True, False, False]]


def test_negate_swaps_black_and_white() -> None:
    grid = grid_from_image(pgm(np.array([[0, 255]])), meta(negate=True))
    assert grid.free.tolist() == [[True, False]]
    assert grid.occupied.tolist() == [[False, True]]


def test_scale_mode_keeps_intermediate_values_and_transparency_is_unknown() -> None:
    grey = np.array([[254, 115, 0, 254]])  # 115: p = 0.549, between the thresholds
    alpha = np.array([[255, 255, 255, 128]])
    grid = grid_from_image(png(np.stack([grey, alpha], axis=-1), "LA"), meta(mode="scale"))
    expected = round((140 / 255 - 0.25) / 0.4 * 100)
    assert grid.data.tolist() == [[0, expected, 100, -1]]
    assert grid.free.tolist() == [[True, False, False, False]]


def test_trinary_averages_alpha_in_like_map_server() -> None:
    # A transparent white pixel: shade (3 * 254 + 0) / 4 / 255, p = 0.253: not free at 0.25.
    rgba = np.array([[[254, 254, 254, 255], [254, 254, 254, 0]]])
    grid = grid_from_image(png(rgba, "RGBA"), meta())
    assert grid.free.tolist() == [[True, False]]
    rgb = np.array([[[255, 0, 0], [254, 254, 254]]])  # red: shade 1/3, p = 0.667: occupied
    grid = grid_from_image(png(rgb, "RGB"), meta())
    assert grid.occupied.tolist() == [[True, False]]


def test_raw_mode_uses_values_as_percent() -> None:
    grid = grid_from_image(pgm(np.array([[0, 20, 50, 100, 255]])), meta(mode="raw", negate=True))
    assert grid.data.tolist() == [[0, 20, 50, 100, -1]]
    assert grid.free.tolist() == [[True, True, False, False, False]]
    assert grid.occupied.tolist() == [[False, False, False, True, False]]


def test_unreadable_image_raises() -> None:
    with pytest.raises(MapFileError, match=r"room\.pgm: cannot decode the image"):
        grid_from_image(b"P5 not really an image", meta(), name="room.pgm")
    with pytest.raises(MapFileError, match=r"room\.pgm: not an image map import reads") as err:
        grid_from_image(b"no image format starts so", meta(), name="room.pgm")
    assert "BytesIO" not in str(err.value)  # Pillow's own message names no file


def test_an_image_whose_header_claims_billions_of_pixels_is_refused_at_once() -> None:
    """A 20-byte PGM header saying 100,000 x 100,000: Pillow's guard stops it before any
    allocation; the error says so in the words of map import, not as an unexpected
    ``DecompressionBombError``."""
    header = b"P5\n100000 100000\n255\n" + bytes(1000)
    with pytest.raises(MapFileError, match=r"huge\.pgm: the image has 10,000,000,000 pixels"):
        grid_from_image(header, meta(), name="huge.pgm")


def test_a_site_map_over_pillows_warning_size_is_read_without_a_warning(
    recwarn: pytest.WarningsRecorder, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Pillow warns of a possible decompression bomb past ``MAX_IMAGE_PIXELS`` (89 M pixels,
    a 470 m square at 5 cm): such a site's map is a map, not a bomb. (The limit is lowered
    here, so that a small image stands for a large one.)"""
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1_000)
    grid = grid_from_image(pgm(np.full((30, 50), 254)), meta())  # 1,500 pixels: warned of
    assert grid.free.shape == (30, 50) and bool(grid.free.all())
    assert not [w for w in recwarn if "decompression" in str(w.message).lower()]
    with pytest.raises(MapFileError, match=r"has 3,000 pixels, more than map import takes"):
        grid_from_image(pgm(np.full((30, 100), 254)), meta())  # past twice the limit


def write_map(folder: Path, pixels: np.ndarray, yaml_text: str = YAML) -> Path:
    (folder / "room.pgm").write_bytes(pgm(pixels))
    path = folder / "room.yaml"
    path.write_text(yaml_text)
    return path


def test_load_grid_resolves_the_image_beside_the_yaml(tmp_path: Path) -> None:
    pixels = np.full((4, 6), 254)
    pixels[0, :] = 0
    grid = load_grid(write_map(tmp_path, pixels))
    assert grid.shape == (4, 6)
    assert grid.resolution == 0.1
    assert grid.origin == (1.0, -2.0, 0.0)
    assert grid.occupied[3].all()  # the image's top row is the grid's last row
    assert grid.free_cells == 18


def test_load_grid_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(MapFileError, match=r"nowhere\.yaml"):
        load_grid(tmp_path / "nowhere.yaml")
    (tmp_path / "lonely.yaml").write_text(YAML)
    with pytest.raises(MapFileError, match=r"image file .*room.pgm' \(named by 'image'"):
        load_grid(tmp_path / "lonely.yaml")
    path = write_map(tmp_path, np.full((2, 2), 254))
    (tmp_path / "room.pgm").write_bytes(b"garbage")
    with pytest.raises(MapFileError, match=r"room\.pgm: not an image map import reads"):
        load_grid(path)
    path.write_text(YAML.replace("resolution: 0.1\n", ""))
    with pytest.raises(MapYamlError, match=r"room.yaml: .*missing required key\(s\) 'resolution'"):
        load_grid(path)


def test_an_image_given_for_the_yaml_is_said_to_be_one(tmp_path: Path) -> None:
    path = write_map(tmp_path, np.full((2, 2), 254))
    image = tmp_path / "room.pgm"
    for given in (image, tmp_path / "room.png"):
        if given.suffix == ".png":
            given.write_bytes(png(np.full((2, 2), 254), "L"))
        with pytest.raises(MapYamlError, match=rf"{given.name}: an image, not the map's YAML"):
            load_grid(given)
    assert load_grid(path).data.shape == (2, 2)  # the YAML itself still loads


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    state = rng.integers(0, 3, size=(7, 9))
    grid = OccupancyGrid(
        data=np.where(state == 0, 0, np.where(state == 1, 100, -1)).astype(np.int8),
        free=state == 0,
        occupied=state == 1,
        resolution=0.05,
        origin=(-3.5, 2.25, 0.4),
    )
    image = save_grid(grid, tmp_path / "saved.yaml")
    assert image.read_bytes() == encode_pgm(grid)
    back = load_grid(tmp_path / "saved.yaml")
    assert np.array_equal(back.free, grid.free)
    assert np.array_equal(back.occupied, grid.occupied)
    assert np.array_equal(back.data, grid.data)
    assert back.origin == grid.origin
    assert back.resolution == grid.resolution


def box_grid(
    rows: int, cols: int, resolution: float, origin: tuple[float, float, float]
) -> OccupancyGrid:
    free = np.zeros((rows, cols), dtype=bool)
    free[1:-1, 1:-1] = True
    return OccupancyGrid(free.astype(np.int8), free, ~free, resolution, origin)


def test_march_rays_hits_cell_edges_exactly() -> None:
    grid = box_grid(12, 22, 0.5, (0.0, 0.0, 0.0))  # free space [0.5, 10.5] x [0.5, 5.5]
    pose = [3.0, 2.0, 0.0]
    angles = [0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi, math.atan2(3.5, 7.5)]
    got = march_rays(grid, pose, angles, 100.0)[0]
    assert got[:4] == pytest.approx([7.5, 3.5, 2.5, 1.5])
    assert got[4] == pytest.approx(math.hypot(7.5, 3.5))
    assert np.isinf(march_rays(grid, pose, [0.0], 7.0)).all()


def test_march_rays_honours_origin_yaw() -> None:
    yaw = 0.7
    grid = box_grid(12, 22, 0.5, (2.0, -1.0, yaw))
    local = np.array([3.0, 2.0])
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.array([2.0 + c * local[0] - s * local[1], -1.0 + s * local[0] + c * local[1]])
    got = march_rays(grid, [*world, yaw], [0.0, 0.5 * math.pi], 100.0)[0]
    assert got == pytest.approx([7.5, 3.5])


def test_grid_rejects_inconsistent_arrays() -> None:
    with pytest.raises(ValueError, match="shape"):
        OccupancyGrid(
            np.zeros((2, 2), np.int8), np.zeros((2, 3), bool), np.zeros((2, 2), bool), 1.0
        )
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGrid(
            np.zeros((2, 2), np.int8), np.zeros((2, 2), bool), np.zeros((2, 2), bool), 0.0
        )
    assert issubclass(MapFileError, MapImportError)


@pytest.mark.parametrize("mode", ["L", "LA", "RGB", "RGBA", "I;16"])
@pytest.mark.parametrize("meta_mode", ["trinary", "scale", "raw"])
def test_a_large_image_is_read_in_bands_with_no_seam(
    mode: str, meta_mode: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Thresholds a pixel value meets exactly (0.2 = 1 - 204/255), where float rounding shows.
    import service.maps.mapimport.grid as grid_module

    rng = np.random.default_rng(5)
    shape = (53, 41)
    if mode == "I;16":
        img = Image.fromarray(rng.integers(0, 65536, shape, dtype=np.uint16))
    elif mode == "L":
        img = Image.fromarray(rng.integers(0, 256, shape, dtype=np.uint8), "L")
    else:
        arr = rng.integers(0, 256, (*shape, len(mode)), dtype=np.uint8)
        if mode in ("LA", "RGBA"):
            arr[..., -1][rng.random(shape) < 0.7] = 255  # most pixels opaque
        img = Image.fromarray(arr, mode)
    buf = io.BytesIO()
    img.save(buf, "PNG")
    meta = MapMetadata("x.png", 0.05, (0.0, 0.0, 0.0), False, 0.6, 0.2, meta_mode)  # type: ignore[arg-type]
    whole = grid_from_image(buf.getvalue(), meta)
    monkeypatch.setattr(grid_module, "BAND_ROWS", 7)  # 8 bands, the last short
    banded = grid_from_image(buf.getvalue(), meta)
    for field in ("data", "free", "occupied"):
        assert np.array_equal(getattr(whole, field), getattr(banded, field)), field
    assert whole.free.any() and whole.occupied.any()


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (("resolution: 0.1", "resolution: 1e-300"), "'resolution' must be between"),
        (("resolution: 0.1", "resolution: 1e300"), "'resolution' must be between"),
        (("resolution: 0.1", "resolution: 1e-5"), "'resolution' must be between"),
        (("origin: [1.0, -2.0, 0.0]", "origin: [1e100, 0, 0]"), "'origin' x and y must be"),
        (("origin: [1.0, -2.0, 0.0]", "origin: [0, -1e20, 0]"), "'origin' x and y must be"),
    ],
)
def test_map_import_refuses_a_scale_no_floor_has(
    edit: tuple[str, str], words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A resolution of 1e-300 m (or 1e300) crashed ``rlutf map import`` with "unexpected error:
    ZeroDivisionError" (or a GEOSException), and an origin of 1e20 m said "the simplified free
    space is empty": a typo, or the wrong unit, is named as one."""
    pixels = np.full((20, 30), 254)
    pixels[[0, -1], :] = pixels[:, [0, -1]] = 0
    (tmp_path / "room.pgm").write_bytes(pgm(pixels))
    (tmp_path / "room.yaml").write_text(YAML.replace(*edit))
    code = main(["map", "import", str(tmp_path / "room.yaml"), "--out", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and words in err and "unexpected error" not in err, err


def test_map_import_takes_the_scales_floors_have(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 30 x 20 cells of 1 km: a scale the YAML check takes, and a map over the default
    # max_map_area, which import refuses unless the settings take it (test_map_limits_cli.py).
    monkeypatch.setenv("RLUTF_MAX_MAP_AREA", "1e12")
    pixels = np.full((20, 30), 254)
    pixels[[0, -1], :] = pixels[:, [0, -1]] = 0
    (tmp_path / "room.pgm").write_bytes(pgm(pixels))
    for resolution, origin in (("0.0001", "[0, 0, 0]"), ("1000", "[-5e6, 4e6, 3.1]")):
        text = YAML.replace("resolution: 0.1", f"resolution: {resolution}")
        (tmp_path / "room.yaml").write_text(
            text.replace("origin: [1.0, -2.0, 0.0]", f"origin: {origin}")
        )
        out = tmp_path / "r.json"
        assert main(["map", "import", str(tmp_path / "room.yaml"), "--out", str(out)]) == 0
