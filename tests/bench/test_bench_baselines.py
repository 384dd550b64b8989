"""The baselines converge: ICP from a displaced start, the particle filter over a run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.baselines import AmclConfig, IcpConfig, ParticleFilter, PointToLineIcp
from bench.baselines.amcl import kld_limit, likelihood_field
from bench.baselines.common import scan_points
from bench.baselines.icp import point_samples
from bench.methods import Method, track
from bench.scenarios import Scenario, simulate
from rlutf.map import Map
from rlutf.sim import LidarModel, OdometryModel, make_building, make_trajectory, simulate_scan


@pytest.mark.parametrize("offset", [(0.2, -0.15, 0.05), (-0.1, 0.25, -0.08)])
def test_icp_converges_from_a_displaced_prediction(offset: tuple[float, float, float]) -> None:
    world = make_building(np.random.default_rng(7))
    rng = np.random.default_rng(8)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(noise=0.0), rng)
    icp = PointToLineIcp(world, truth + np.array(offset), IcpConfig())
    est = icp.update(np.zeros(3), scan)
    assert est.pose is not None and est.status == "corrected"
    assert math.hypot(*(est.pose[:2] - truth[:2])) < 1e-3
    assert abs(est.pose[2] - truth[2]) < 1e-3


def test_icp_with_noise_reaches_millimetres() -> None:
    world = make_building(np.random.default_rng(9))
    rng = np.random.default_rng(10)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(noise=0.01), rng)
    est = PointToLineIcp(world, truth + np.array([0.1, 0.1, 0.03])).update(np.zeros(3), scan)
    assert est.pose is not None
    assert math.hypot(*(est.pose[:2] - truth[:2])) < 0.005


def test_likelihood_field_is_zero_on_walls_and_capped() -> None:
    world = make_building(np.random.default_rng(11))
    field = likelihood_field(world, 0.05, 2.0)
    seg = world.segments
    mid = 0.5 * (seg[:, :2] + seg[:, 2:])
    assert np.all(field.lookup(mid) == 0.0)
    assert field.lookup(np.array([[-100.0, -100.0]]))[0] == 2.0
    assert field.distance.max() <= 2.0


def test_kld_limit_grows_with_bins_within_bounds() -> None:
    cfg = AmclConfig()
    limits = kld_limit(np.array([1, 2, 10, 100, 1000]), cfg)
    assert limits[0] == cfg.max_particles
    assert np.all(np.diff(limits[1:]) >= 0)
    assert limits.min() >= cfg.min_particles and limits.max() <= cfg.max_particles


def test_particle_filter_tracks_a_run() -> None:
    scenario = Scenario("pf", "test", steps=80, odometry=OdometryModel(), lidar=LidarModel())
    run = simulate(scenario, 5)
    cfg = AmclConfig(max_particles=800, min_particles=300)
    method = Method("amcl", "AMCL", lambda w, p, s: ParticleFilter(w, p, cfg, seed=s))
    trace = track(method, run, seed=1)
    err = np.hypot(*(trace.poses[:, :2] - run.truth[1:, :2]).T)
    assert np.all(np.isfinite(err))
    assert float(np.sqrt(np.mean(err[20:] ** 2))) < 0.15
    assert "corrected" in trace.status and "predicted" in trace.status


def test_particle_filter_corrects_a_wrong_start() -> None:
    # Started 0.3 m off with the default cloud (0.5 m), it pulls towards the truth.
    world = make_building(np.random.default_rng(12))
    rng = np.random.default_rng(13)
    truth = make_trajectory(world, rng, 1)[0]
    pf = ParticleFilter(world, truth + np.array([0.3, 0.0, 0.0]), AmclConfig(), seed=2)
    turn = np.array([0.0, 0.0, 0.25])
    for _ in range(15):  # turning in place: a filter update every time
        truth = truth + turn
        est = pf.update(turn, simulate_scan(world, truth, LidarModel(), rng))
    assert est.pose is not None
    assert math.hypot(*(est.pose[:2] - truth[:2])) < 0.15


def _cloud(
    world: Map, poses: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """End points of noise-free scans at ``poses`` in the map frame, and their sensors."""
    points, sensors = [], []
    for pose in poses:
        scan = simulate_scan(world, pose, LidarModel(noise=0.0), rng)
        ok = scan.valid()
        local = scan_points(scan.ranges[ok], scan.angles[ok], scan.sensor_offset)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        points.append(local @ np.array([[c, s], [-s, c]]) + pose[:2])
        sensors.append(np.broadcast_to(pose[:2], points[-1].shape))
    return np.vstack(points), np.vstack(sensors)


def test_point_samples_thin_and_face_their_sensors() -> None:
    world = make_building(np.random.default_rng(12))
    rng = np.random.default_rng(13)
    poses = make_trajectory(world, rng, 5)
    points, sensors = _cloud(world, poses, rng)
    samples = point_samples(points, sensors, spacing=0.02)
    cells = np.floor(samples.points / 0.02).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(samples.points) < len(points)
    assert np.allclose(samples.points, points[samples.walls])
    assert np.allclose(np.hypot(*samples.normals.T), 1.0)
    towards = np.einsum("ij,ij->i", samples.normals, sensors[samples.walls] - samples.points)
    assert np.all(towards > 0.0)


def test_icp_on_raw_points_converges_like_on_the_map() -> None:
    world = make_building(np.random.default_rng(14))
    rng = np.random.default_rng(15)
    poses = make_trajectory(world, rng, 6)
    points, sensors = _cloud(world, poses[:-1], rng)
    samples = point_samples(points, sensors)
    truth = poses[-1]
    scan = simulate_scan(world, truth, LidarModel(noise=0.0), rng)
    icp = PointToLineIcp(None, truth + np.array([0.1, -0.08, 0.03]), IcpConfig(), samples)
    est = icp.update(np.zeros(3), scan)
    assert est.pose is not None and est.status == "corrected"
    assert math.hypot(*(est.pose[:2] - truth[:2])) < 0.01
    with pytest.raises(ValueError, match="world"):
        PointToLineIcp(None, truth)
