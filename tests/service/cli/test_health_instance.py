"""``rlutf health --instance NAME`` with no instance of that name, the service running: it said
"no instance answered ... is `rlutf serve` running?", sending the operator to a service that
runs; it names the live instances."""

from __future__ import annotations

from pathlib import Path

import pytest
from service_harness import running_bench

from service.cli.main import main

pytestmark = pytest.mark.integration


def test_health_of_an_instance_that_is_not_there_names_the_live_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        name = bench.service.settings.instance
        e = ["-e", bench.endpoint, "--timeout", "1"]
        assert main(["health", "--instance", "nope", *e]) == 1
        err = capsys.readouterr().err
        assert "no instance 'nope'" in err and f"'{name}'" in err, err
        assert "is `rlutf serve` running" not in err, err
        assert main(["health", "--instance", name, *e]) == 0
        assert name in capsys.readouterr().out
        # A prefix no instance is on is still said so (nothing runs there).
        assert main(["health", "--instance", "nope", *e, "--prefix", "elsewhere"]) == 1
        assert "is `rlutf serve` running" in capsys.readouterr().err
