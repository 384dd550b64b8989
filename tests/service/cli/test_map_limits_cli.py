"""`rlutf map import` writes only maps the service takes with the settings in effect (WIRE.md
v1.2: every map import or build writes is accepted by the storage, the service and replay)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.cli.main import main


def _grid(folder: Path, cells: int, resolution: float) -> Path:
    """A square room of ``cells`` x ``cells`` at ``resolution`` m, walls around, nothing in it."""
    grid = np.full((cells, cells), 254, dtype=np.uint8)
    grid[:2, :] = grid[-2:, :] = grid[:, :2] = grid[:, -2:] = 0
    (folder / "hall.pgm").write_bytes(b"P5\n%d %d\n255\n" % (cells, cells) + grid.tobytes())
    yaml = folder / "hall.yaml"
    yaml.write_text(
        f"image: hall.pgm\nresolution: {resolution}\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    return yaml


def test_map_import_refuses_a_map_over_the_area_the_service_takes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A grid of 400 x 400 cells of 1 m: 160,000 m2, over max_map_area's 100,000. Before, the
    import wrote it (exit 0) and only the put was refused by the store, after the operator had
    copied the file to the site."""
    monkeypatch.delenv("RLUTF_MAX_MAP_AREA", raising=False)
    yaml, out = _grid(tmp_path, 400, 1.0), tmp_path / "hall.json"
    assert main(["map", "import", str(yaml), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "max_map_area" in err and "RLUTF_MAX_MAP_AREA=" in err, err
    assert not out.exists()
    # With a limit that holds it (in the environment, as the service reads it): written.
    monkeypatch.setenv("RLUTF_MAX_MAP_AREA", "200000")
    assert main(["map", "import", str(yaml), "--out", str(out)]) == 0
    assert out.exists()
