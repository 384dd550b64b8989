"""`rlutf map list` names a map the store holds but no longer serves (its file changed on disk)
and what to do, instead of leaving it out (or saying "no maps stored yet", exit 0)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from service_harness import running_bench

from service.cli.main import main

pytestmark = pytest.mark.integration


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_map_list_names_a_map_held_but_not_served(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        e = bench.endpoint
        bench.put_map("m1")
        code, out, _ = _cli(capsys, "map", "list", "-e", e)
        assert code == 0 and out.splitlines()[1].split()[:2] == ["m1", "1"]
        payload = (bench.store / "m1.json").read_bytes()
        (bench.store / "m1.json").write_bytes(payload[: len(payload) // 2])  # cut short
        time.sleep(1.1)  # the store's last read is answered again for a second
        code, out, err = _cli(capsys, "map", "list", "-e", e)
        assert code == 1, (out, err)
        assert "map m1 version 1: held by the map store but not served" in err
        assert "rlutf map put FILE --id m1" in err and "no maps stored" not in err
