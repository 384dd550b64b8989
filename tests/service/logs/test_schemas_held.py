"""A recorder holds every schema it may log from its creation on: a package reinstalled (or its
files removed) under a running service cannot make a channel schema-less, and a package that
lacks a schema stops the recorder at its start."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcaplog_fixtures import simulated_inputs, write_log

from schemas import SCHEMA_NAMES
from service.cli.main import main
from service.logs import foxglove
from service.logs.mcapfile import VIEW_SCHEMA_NAMES, Record, load_schemas
from service.logs.replay import replay

REPO = Path(__file__).resolve().parents[3]

#: Run in a copy of the package: a recorder is created, then the package's schema folders are
#: removed (as ``pip install`` under a running service removes and rewrites them), then the
#: messages are recorded, each topic's first message after the removal.
_RECORD = textwrap.dedent(
    """
    import json, shutil, sys
    from pathlib import Path
    from service.logs.mcaplog import McapRecorder
    from service.logs.mcapread import LogFile

    import schemas
    pkg, src, out = map(Path, sys.argv[1:4])
    assert Path(schemas.__file__).is_relative_to(pkg), schemas.__file__  # the copy's
    rec = McapRecorder(out, instance="demo", foxglove=True)
    shutil.rmtree(pkg / "schemas" / "jsonschema")
    shutil.rmtree(pkg / "service" / "logs" / "foxglove_schemas")
    with LogFile(src) as lf:
        rec.set_config(lf.config())
        for r in lf.messages():
            rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    rec.close()
    print(json.dumps([str(p) for p in rec.files]))
    """
)


def _package_copy(into: Path) -> Path:
    for name in ("rlutf", "schemas", "service"):
        shutil.copytree(
            REPO / name, into / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
    return into


def _inputs_with_poses(scratch: Path) -> Path:
    """Two robots' inputs and the poses the engine computes for them, in one log."""
    inputs = simulated_inputs(("r1", "r2"), steps=6, beams=90)
    computed = replay([write_log(scratch / "inputs.mcap", inputs)])
    received = {
        (r.topic.split("/")[2], r.publish_time_ns): r.log_time_ns
        for r in inputs
        if r.schema_name == "rlutf.LaserScan"
    }
    poses = [
        Record(
            f"rlutf/robots/{robot}/pose",
            "rlutf.PoseEstimate",
            p.payload,
            received[(robot, p.stamp_ns)],
            p.stamp_ns,
        )
        for robot, records in computed.recomputed.items()
        for p in records
    ]
    assert poses
    records = sorted([*inputs, *poses], key=lambda r: r.log_time_ns)
    return write_log(scratch / "records.mcap", records, computed.config.settings)


def test_schema_files_removed_after_start_change_nothing_logged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pkg = _package_copy(tmp_path / "pkg")
    src = _inputs_with_poses(tmp_path)
    logs = tmp_path / "logs"
    env = {**os.environ, "PYTHONPATH": str(pkg)}
    done = subprocess.run(
        [sys.executable, "-c", _RECORD, str(pkg), str(src), str(logs)],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert not (pkg / "schemas" / "jsonschema").exists()
    (path,) = logs.glob("*.mcap")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {c.topic for c in summary.channels.values()}
    assert "rlutf/robots/r2/pose" in topics and "/foxglove/tf" in topics
    for channel in summary.channels.values():
        assert channel.schema_id != 0, channel.topic
        schema = summary.schemas[channel.schema_id]
        if schema.name.startswith("rlutf."):
            folder = REPO / "schemas" / "jsonschema"
        else:
            folder = REPO / "service" / "logs" / "foxglove_schemas"
        assert schema.data == (folder / f"{schema.name}.json").read_bytes()
    capsys.readouterr()
    code = main(["replay", str(logs), "--quiet"])
    out, err = capsys.readouterr()
    assert code == 0, out + err
    assert "without a schema" not in out + err


def test_a_schema_missing_at_start_stops_the_service_at_start(tmp_path: Path) -> None:
    # every schema a log may name is read, the views' too
    assert set(load_schemas()) == {*SCHEMA_NAMES.values(), *foxglove.SCHEMA_NAMES}
    assert set(VIEW_SCHEMA_NAMES) == set(foxglove.SCHEMA_NAMES)
    pkg = _package_copy(tmp_path / "pkg")
    (pkg / "schemas" / "jsonschema" / "rlutf.Odometry.json").unlink()
    env = {**os.environ, "PYTHONPATH": str(pkg)}
    flags = ["--processes", "0", "-l", "tcp/127.0.0.1:0"]
    for name in ("record", "store", "state"):
        flags += [f"--{name}", str(tmp_path / name)]
    done = subprocess.run(
        [sys.executable, "-m", "service", "serve", *flags],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 1, done.stderr
    assert "rlutf serve: no JSON Schema for rlutf.Odometry" in done.stderr
    assert "reinstall" in done.stderr and "Traceback" not in done.stderr
    assert not list((tmp_path / "record").glob("*.mcap*"))
