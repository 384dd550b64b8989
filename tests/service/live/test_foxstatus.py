"""The fleet status entity of the live view: 1-sigma ellipse, label, schema."""

from __future__ import annotations

import json
import math

import jsonschema
import numpy as np

from service.live.foxstatus import label, sigma_ellipse, status_entity, status_update
from service.logs.foxglove import embedded_dir


def _pose(cov: list[float] | None, **kw: object) -> dict[str, object]:
    pose: dict[str, object] = {
        "stamp_ns": 1_700_000_000_123_000_000,
        "robot_id": "r1",
        "map_id": "m1",
        "x": 1.0,
        "y": 2.0,
        "theta": 0.5,
        "status": "tracking",
        "discrepancy": 0.1,
        "iterations": 2,
        "covariance": cov,
    }
    pose.update(kw)
    return pose


def test_the_ellipse_is_the_covariances_eigen_decomposition() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        a = rng.normal(size=(2, 2))
        xy = a @ a.T + 1e-6 * np.eye(2)
        cov = [xy[0, 0], xy[0, 1], 0.0, xy[1, 0], xy[1, 1], 0.0, 0.0, 0.0, 1e-4]
        major, minor, angle = sigma_ellipse(cov)
        values, vectors = np.linalg.eigh(xy)
        assert math.isclose(major, math.sqrt(values[1]), rel_tol=1e-9)
        assert math.isclose(minor, math.sqrt(values[0]), rel_tol=1e-6, abs_tol=1e-9)
        # the major axis is the eigenvector of the larger eigenvalue (up to its sign)
        direction = np.array([math.cos(angle), math.sin(angle)])
        assert abs(abs(direction @ vectors[:, 1]) - 1.0) < 1e-9


def test_label_reads_in_centimetres_and_degrees() -> None:
    cov = [0.02**2, 0.0, 0.0, 0.0, 0.01**2, 0.0, 0.0, 0.0, math.radians(0.5) ** 2]
    assert label("r1", _pose(cov)) == "r1 tracking ±2.0 cm ±0.5°"
    assert label("r1", _pose(None, status="lost")) == "r1 lost"
    hyps = [{"x": 0.0, "y": 0.0, "theta": 0.0, "score": 0.5}] * 2
    assert label("r1", _pose(None, hypotheses=hyps)) == "r1 relocalizing (2 hypotheses)"


def test_the_update_validates_against_foxglove_scene_update() -> None:
    schema = json.loads((embedded_dir() / "foxglove.SceneUpdate.json").read_text())
    cov = [1e-4, 0.0, 0.0, 0.0, 4e-4, 0.0, 0.0, 0.0, 1e-5]
    entities = [status_entity("r1", _pose(cov), "map"), status_entity("r2", _pose(None), "map")]
    update = json.loads(status_update(entities))
    jsonschema.validate(update, schema)
    r1, r2 = update["entities"]
    assert (r1["id"], r2["id"]) == ("robot/r1", "robot/r2")
    assert len(r1["cylinders"]) == 1 and not r2["cylinders"]  # no covariance, no ellipse
    size = r1["cylinders"][0]["size"]
    assert math.isclose(size["x"], 0.05) and math.isclose(size["y"], 0.05)  # the minimum
    assert r1["timestamp"] == {"sec": 1_700_000_000, "nsec": 123_000_000}
