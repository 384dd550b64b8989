"""A FIFO or a device where a file is expected is refused at once, by every command that reads
one. A FIFO no one wrote to hung ``rlutf log info``, ``replay``, ``log recover``, ``map import``
(as the YAML or the image it names), ``map show`` and ``map build`` (and ``--ros2``: a FIFO as
the bag or in its folder) for ever; ``/dev/zero`` was
read until memory ran out (an "unexpected error: MemoryError" under a ulimit, the OOM killer
without)."""

from __future__ import annotations

import errno
import json
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.cli.main import main
from service.infile import open_regular, read_regular
from service.logs.mcapfile import LogWriter, Record

#: A command that blocks on the FIFO is released (by a writer that opens and closes it) after
#: this long, so that a regression fails the test instead of hanging it.
RELEASE_S = 10.0


def _release(fifo: Path, stop: threading.Event) -> None:
    """Open the FIFO for writing (and close it: EOF to its reader) once RELEASE_S has passed."""
    deadline = time.monotonic() + RELEASE_S
    while not stop.wait(0.05):
        if time.monotonic() < deadline:
            continue
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError as err:
            if err.errno != errno.ENXIO:  # ENXIO: no reader yet
                return


@pytest.fixture
def fifo(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "pipe.mcap"
    os.mkfifo(path)
    stop = threading.Event()
    releaser = threading.Thread(target=_release, args=(path, stop), daemon=True)
    releaser.start()
    yield path
    stop.set()
    releaser.join()


def _yaml(tmp_path: Path, image: str) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(
        f"image: {image}\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.25\n"
    )
    return path


@pytest.mark.parametrize(
    "argv",
    [
        ["log", "info", "{fifo}"],
        ["replay", "{fifo}", "--quiet", "--jobs", "1"],
        ["log", "views", "{fifo}", "--out", "{tmp}/views.mcap"],
        ["log", "recover", "{fifo}", "{tmp}/fixed.mcap"],
        ["map", "import", "{fifo}", "--out", "{tmp}/site.json"],
        ["map", "import", "{yaml}", "--out", "{tmp}/site.json"],
        ["map", "show", "{fifo}", "--out", "{tmp}/site.png"],
        ["map", "build", "{fifo}", "--out", "{tmp}/site.json"],
        ["map", "build", "--ros2", "{fifo}", "--out", "{tmp}/site.json"],
        ["replay", "--ros2", "{fifo}", "--map", "{tmp}/site.json", "--initial-pose", "0,0,0"],
        ["replay", "--ros2", "{tmp}", "--map", "{tmp}/site.json", "--initial-pose", "0,0,0"],
    ],
)
def test_a_fifo_is_refused_at_once(
    argv: list[str], fifo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    names = {"fifo": str(fifo), "tmp": str(tmp_path), "yaml": str(_yaml(tmp_path, str(fifo)))}
    room = {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]]}
    (tmp_path / "site.json").write_text(json.dumps({"map_id": "site", "geometry": room}))
    started = time.monotonic()
    code = main([a.format(**names) for a in argv])
    _, err = capsys.readouterr()
    assert time.monotonic() - started < RELEASE_S / 2, "it waited for a writer"
    assert code in (1, 2) and "FIFO (named pipe), not a regular file" in err, err
    assert "Traceback" not in err and "unexpected error" not in err


@pytest.mark.parametrize(
    "argv",
    [
        ["map", "import", "{yaml}", "--out", "{tmp}/site.json"],
        ["map", "show", "/dev/zero", "--out", "{tmp}/site.png"],
        ["map", "build", "/dev/zero", "--out", "{tmp}/site.json"],
        ["replay", "{tmp}/none.mcap", "--settings", "/dev/zero", "--quiet"],
    ],
)
def test_a_device_is_refused_not_read_until_memory_runs_out(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if not Path("/dev/zero").exists():
        pytest.skip("no /dev/zero")
    names = {"tmp": str(tmp_path), "yaml": str(_yaml(tmp_path, "/dev/zero"))}
    with open(tmp_path / "none.mcap", "wb") as stream:  # a log with one input, a map
        writer = LogWriter(stream)
        room = {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]]}
        payload = json.dumps({"map_id": "m1", "version": 1, "geometry": room}).encode()
        writer.write_all([Record("rlutf/maps/m1", "rlutf.Map", payload, 1, 1)])
        writer.finish()
    code = main([a.format(**names) for a in argv])
    _, err = capsys.readouterr()
    assert code in (1, 2) and "a device, not a regular file" in err, err


def test_map_put_names_a_fifo_for_what_it_is(
    fifo: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["map", "put", str(fifo)]) == 2
    assert "is not a regular file (a FIFO, a device or a socket)" in capsys.readouterr().err


def test_open_regular_reads_a_file_and_names_a_folder(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_bytes(b"abc")
    assert read_regular(tmp_path / "a.txt") == b"abc"
    with pytest.raises(OSError) as caught:
        open_regular(tmp_path)
    assert caught.value.errno == errno.EISDIR
    with pytest.raises(FileNotFoundError):
        open_regular(tmp_path / "missing")


def test_a_file_over_its_bound_is_refused_before_more_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """What a command reads whole has a size past which no real input goes: a map's YAML is a
    few hundred bytes, and a 2 MB one (a wrong file, a generated one gone wrong) was read
    whole; now it is refused by name, exit 2."""
    path = tmp_path / "f"
    path.write_bytes(b"x" * 100)
    assert read_regular(path, 100) == b"x" * 100
    with pytest.raises(OSError, match=r"larger than 99 bytes") as err:
        read_regular(path, 99)
    assert err.value.errno == errno.EFBIG
    yaml = tmp_path / "site.yaml"
    yaml.write_text("image: site.pgm\n" + "#" * (2 << 20) + "\n")
    assert main(["map", "import", str(yaml), "--out", str(tmp_path / "m.json")]) == 2
    assert "larger than 1,048,576 bytes" in capsys.readouterr().err
