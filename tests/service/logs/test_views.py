"""Live logs hold the WIRE.md channels only unless ``record_views``; ``rlutf log views`` and
``rlutf replay`` write the Foxglove views from a log."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs

from service.cli.main import main
from service.config import Settings
from service.logs.foxglove import SCHEMA_NAMES, TF_TOPIC
from service.logs.mcapfile import Record
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile, NotALog
from service.logs.recording import make_recorder
from service.logs.replay import replay
from service.logs.views import write_views

CONFIG = {"prefix": "rlutf", "instance": "v1", "workers": 0}
VIEWS = set(SCHEMA_NAMES)


def _record(rec: McapRecorder, records: list[Record]) -> list[Path]:
    rec.set_config(CONFIG)
    for r in records:
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    rec.close()
    return rec.files


def _all(path: Path) -> list[Record]:
    with LogFile(path) as lf:
        return list(lf.messages())


def _wire(records: list[Record]) -> list[Record]:
    return [r for r in records if r.schema_name.startswith("rlutf.")]


@pytest.fixture(scope="module")
def inputs() -> list[Record]:
    return simulated_inputs(steps=8)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory, inputs: list[Record]) -> dict[str, Path]:
    """The same inputs recorded as the service does by default, and with ``record_views``."""
    folder = tmp_path_factory.mktemp("rec")
    out = {}
    for name, views in (("plain", False), ("views", True)):
        settings = Settings(record_dir=folder / name, instance="v1", record_views=views)
        rec = make_recorder(settings)
        assert isinstance(rec, McapRecorder)
        (out[name],) = _record(rec, inputs)
    return out


def test_live_log_has_no_views_by_default_and_has_them_with_the_setting(
    logs: dict[str, Path], inputs: list[Record]
) -> None:
    assert Settings().record_views is False
    plain, viewed = _all(logs["plain"]), _all(logs["views"])
    assert not [r for r in plain if r.schema_name in VIEWS or r.topic.startswith("/foxglove/")]
    topics = {r.topic for r in viewed if r.schema_name in VIEWS}
    assert {"/foxglove/maps/m1", "/foxglove/robots/r1/scan", TF_TOPIC} <= topics
    # the WIRE.md channels are the same, message for message, byte for byte, with or without
    assert _wire(plain) == _wire(viewed) == inputs
    with LogFile(logs["plain"]) as a, LogFile(logs["views"]) as b:
        assert a.config() == b.config() == CONFIG


def test_log_views_writes_what_the_recorder_wrote_with_the_setting(
    logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "with-views.mcap"
    assert main(["log", "views", str(logs["plain"]), "--out", str(out)]) == 0
    assert "Foxglove views" in capsys.readouterr().out
    # every message, views included, as the live recorder writes them with record_views
    assert _all(out) == _all(logs["views"])
    with LogFile(logs["plain"]) as src, LogFile(out) as copy:
        assert copy.metadata() == src.metadata()  # rlutf.config and rlutf.run: the same run
        assert copy.schemas().items() >= src.schemas().items()
    # views already in a log are written anew, not twice
    again = write_views(out, tmp_path / "again.mcap")
    assert again.replaced == again.views > 0
    assert _all(tmp_path / "again.mcap") == _all(out)


def test_log_views_of_several_logs_into_a_folder(
    logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "views"
    assert main(["log", "views", str(logs["plain"]), str(logs["views"]), "--out", str(folder)]) == 0
    for src in (logs["plain"], logs["views"]):
        assert _all(folder / src.name) == _all(logs["views"])
    code = main(["log", "views", str(logs["plain"]), "--out", str(logs["plain"])])
    assert code == 2 and "must not be an input" in capsys.readouterr().err
    code = main(["log", "views", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "x")])
    assert code == 2 and "missing.mcap" in capsys.readouterr().err
    with pytest.raises(NotALog):
        write_views(logs["plain"], logs["plain"])


def test_replay_of_a_log_without_views_writes_them(logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "replayed.mcap"
    result = replay([logs["plain"]], out)
    topics = {r.topic for r in _all(out) if r.schema_name in VIEWS}
    assert {"/foxglove/robots/r1/scan", "/foxglove/robots/r1/pose", TF_TOPIC} <= topics
    assert sum(len(v) for v in result.recomputed.values()) > 0
