"""A likelihood-field particle filter run the way ROS AMCL (Nav2 ``nav2_amcl``) runs it.

Faithful to AMCL's algorithm and to Nav2's documented defaults (:class:`AmclConfig`):

* **Map**: the polygon map rasterised at 5 cm (a cell is an obstacle if a wall crosses it or
  its centre is outside the free space, as in a grid built from scan hits); the likelihood
  field is the distance from each cell to the nearest obstacle
  (:func:`scipy.ndimage.distance_transform_edt`), capped at ``laser_likelihood_max_dist``;
  points off the map get the cap, as in AMCL.
* **Motion**: the differential-drive ``sample_motion_model_odometry`` of Nav2's
  ``DifferentialMotionModel`` (rot1, trans, rot2 with ``alpha1..alpha4``).
* **Sensor**: ``LikelihoodFieldModel``: at most ``max_beams`` beams, evenly strided as AMCL
  strides them; per beam ``pz = z_hit * exp(-d^2 / (2 sigma_hit^2)) + z_rand / range_max``;
  a particle's weight is multiplied by ``1 + sum(pz^3)`` (AMCL's ad hoc combination).
* **Filter updates** only after the robot moved ``update_min_d`` or turned ``update_min_a``
  since the last one (forced on the first scan). Between them AMCL's pose is its last
  estimate carried along by odometry (map->odom held fixed), which is what is reported.
* **Resampling** every ``resample_interval`` updates, low-variance (systematic), with the
  sample count set by KLD sampling (``pf_err``, ``pf_z``; histogram bins of 0.5 m, 0.5 m and
  10 degrees, as AMCL's k-d tree) between ``min_particles`` and ``max_particles``. AMCL's
  own resampler is multinomial; low-variance has the same expectation and less noise.
  Recovery (``recovery_alpha_slow/fast``) is off by default in Nav2 and here.
* **Estimate**: particles are clustered by connected occupied bins (AMCL's
  ``pf_cluster_stats``); the reported pose is the weighted mean of the heaviest cluster.
* **Start**: particles drawn around the initial pose with RViz's "2D Pose Estimate"
  covariance (0.5 m and pi/12 rad standard deviations), AMCL's default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy import ndimage

from bench.baselines.common import Estimate, FloatArray
from bench.baselines.icp import wall_samples
from rlutf.map import Map
from rlutf.motion import compose, relative, wrap_angle
from rlutf.scan import Scan

_BIN = np.array([0.5, 0.5, math.radians(10.0)])


@dataclass(frozen=True)
class AmclConfig:
    """AMCL parameters; the defaults are Nav2's (``nav2_amcl``, documented defaults).

    Attributes:
        min_particles: fewest particles.
        max_particles: most particles (and the initial count).
        alpha1: rotation noise from rotation.
        alpha2: rotation noise from translation.
        alpha3: translation noise from translation.
        alpha4: translation noise from rotation.
        z_hit: weight of the Gaussian hit term.
        z_rand: weight of the uniform random term.
        sigma_hit: standard deviation of the hit term, metres.
        laser_likelihood_max_dist: cap of the distance field, metres.
        laser_max_range: ranges are capped at ``min(scan range_max, this)``, metres.
        max_beams: beams used per scan.
        update_min_d: translation that triggers a filter update, metres (negative: every
            scan triggers one).
        update_min_a: rotation that triggers a filter update, radians.
        resample_interval: filter updates between resamplings.
        pf_err: KLD error bound.
        pf_z: KLD quantile parameter, used as AMCL uses it (directly, not as a quantile).
        resolution: cell size of the rasterised map, metres.
        initial_sigma_xy: initial standard deviation in x and y, metres.
        initial_sigma_theta: initial standard deviation in heading, radians.
    """

    min_particles: int = 500
    max_particles: int = 2000
    alpha1: float = 0.2
    alpha2: float = 0.2
    alpha3: float = 0.2
    alpha4: float = 0.2
    z_hit: float = 0.5
    z_rand: float = 0.5
    sigma_hit: float = 0.2
    laser_likelihood_max_dist: float = 2.0
    laser_max_range: float = 100.0
    max_beams: int = 60
    update_min_d: float = 0.25
    update_min_a: float = 0.2
    resample_interval: int = 1
    pf_err: float = 0.05
    pf_z: float = 0.99
    resolution: float = 0.05
    initial_sigma_xy: float = 0.5
    initial_sigma_theta: float = math.pi / 12.0


@dataclass(frozen=True, eq=False)
class LikelihoodField:
    """Distance to the nearest obstacle on a grid, capped.

    Attributes:
        origin: ``(2,)`` map-frame position of the lower-left corner of cell ``(0, 0)``.
        resolution: cell size, metres.
        distance: ``(rows, cols)`` distances, metres.
        cap: distance given to points off the grid, metres.
    """

    origin: FloatArray
    resolution: float
    distance: FloatArray
    cap: float

    def lookup(self, points: FloatArray) -> FloatArray:
        """Distances at ``(..., 2)`` map-frame points (the cap off the grid)."""
        ij = np.floor((points - self.origin) / self.resolution).astype(np.int64)
        rows, cols = self.distance.shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < cols) & (ij[..., 1] >= 0) & (ij[..., 1] < rows)
        col = np.clip(ij[..., 0], 0, cols - 1)
        row = np.clip(ij[..., 1], 0, rows - 1)
        return np.where(inside, self.distance[row, col], self.cap)


@cache
def likelihood_field(world: Map, resolution: float, cap: float) -> LikelihoodField:
    """Rasterise ``world`` and compute its capped obstacle-distance field."""
    minx, miny, maxx, maxy = world.bounds
    origin = np.array([minx - resolution, miny - resolution])
    cols = math.ceil((maxx - minx) / resolution) + 2
    rows = math.ceil((maxy - miny) / resolution) + 2
    xs = origin[0] + (np.arange(cols) + 0.5) * resolution
    ys = origin[1] + (np.arange(rows) + 0.5) * resolution
    gx, gy = np.meshgrid(xs, ys)
    free = shapely.contains_xy(world.geometry, gx.ravel(), gy.ravel()).reshape(rows, cols)
    # Cells a wall passes through are obstacles too, as in a grid built from scan hits: a beam
    # ending on a wall then lands in an obstacle cell (distance 0) from either side, instead
    # of in a free cell half the time, which would pull the estimate towards the walls.
    on_wall = wall_samples(world, resolution / 4.0).points
    cell = np.floor((on_wall - origin) / resolution).astype(np.int64)
    free[cell[:, 1], cell[:, 0]] = False
    distance = np.minimum(ndimage.distance_transform_edt(free) * resolution, cap)
    return LikelihoodField(origin, resolution, np.asarray(distance, dtype=np.float64), cap)


def kld_limit(k: NDArray[np.int64], config: AmclConfig) -> NDArray[np.int64]:
    """AMCL's ``pf_resample_limit``: particles needed for ``k`` occupied histogram bins."""
    kk = np.maximum(np.asarray(k, dtype=np.float64), 2.0)
    b = 2.0 / (9.0 * (kk - 1.0))
    x = 1.0 - b + np.sqrt(b) * config.pf_z
    n = np.ceil((kk - 1.0) / (2.0 * config.pf_err) * x**3)
    n = np.clip(n, config.min_particles, config.max_particles)
    return np.where(np.asarray(k) <= 1, config.max_particles, n).astype(np.int64)


class ParticleFilter:
    """Tracks a robot with an AMCL-style likelihood-field particle filter.

    Args:
        world: the map.
        pose: ``(3,)`` initial pose.
        config: parameters.
        seed: seed of the filter's random generator.
    """

    def __init__(
        self, world: Map, pose: FloatArray, config: AmclConfig | None = None, seed: int = 0
    ) -> None:
        self.config = cfg = config or AmclConfig()
        self._field = likelihood_field(world, cfg.resolution, cfg.laser_likelihood_max_dist)
        self._rng = np.random.default_rng(seed)
        sigma = np.array([cfg.initial_sigma_xy, cfg.initial_sigma_xy, cfg.initial_sigma_theta])
        self.particles = pose + self._rng.normal(0.0, 1.0, (cfg.max_particles, 3)) * sigma
        self.weights = np.full(cfg.max_particles, 1.0 / cfg.max_particles)
        self._estimate = np.asarray(pose, dtype=np.float64).copy()
        # Odometry pose, in an odometry frame that starts at the initial pose (the frame in
        # which AMCL tests update_min_d on x and y).
        self._odom = self._estimate.copy()
        self._odom_at_update = self._odom.copy()
        self._updates = 0
        self._first = True

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Accumulate ``motion``; run a filter update if the robot moved enough."""
        cfg = self.config
        self._odom = compose(self._odom, motion)
        delta = self._odom - self._odom_at_update
        delta[2] = float(wrap_angle(delta[2]))
        moved = (
            abs(delta[0]) > cfg.update_min_d
            or abs(delta[1]) > cfg.update_min_d
            or abs(delta[2]) > cfg.update_min_a
        )
        if not (moved or self._first):
            since = relative(self._odom_at_update, self._odom)
            return Estimate(compose(self._estimate, since), "predicted")
        self._first = False
        self._move(relative(self._odom_at_update, self._odom))
        self._odom_at_update = self._odom.copy()
        self._weigh(scan)
        self._updates += 1
        self._estimate = self._cluster_mean()
        if self._updates % cfg.resample_interval == 0:
            self._resample()
        return Estimate(self._estimate.copy(), "corrected")

    def _move(self, u: FloatArray) -> None:
        cfg = self.config
        trans = math.hypot(u[0], u[1])
        rot1 = 0.0 if trans < 0.01 else math.atan2(u[1], u[0])
        rot2 = float(wrap_angle(u[2] - rot1))

        def noise_of(a: float) -> float:
            return min(abs(float(wrap_angle(a))), abs(float(wrap_angle(a - math.pi))))

        n1, n2 = noise_of(rot1), noise_of(rot2)
        count = len(self.particles)
        g = self._rng.normal(0.0, 1.0, (3, count))
        rot1_hat = rot1 - g[0] * math.sqrt(cfg.alpha1 * n1 * n1 + cfg.alpha2 * trans * trans)
        trans_hat = trans - g[1] * math.sqrt(
            cfg.alpha3 * trans * trans + cfg.alpha4 * n1 * n1 + cfg.alpha4 * n2 * n2
        )
        rot2_hat = rot2 - g[2] * math.sqrt(cfg.alpha1 * n2 * n2 + cfg.alpha2 * trans * trans)
        p = self.particles
        heading = p[:, 2] + rot1_hat
        p[:, 0] += trans_hat * np.cos(heading)
        p[:, 1] += trans_hat * np.sin(heading)
        p[:, 2] = wrap_angle(p[:, 2] + rot1_hat + rot2_hat)

    def _weigh(self, scan: Scan) -> None:
        cfg = self.config
        count = len(scan.ranges)
        step = max((count - 1) // max(cfg.max_beams - 1, 1), 1)
        index = np.arange(0, count, step)
        ranges = scan.ranges[index]
        angles = scan.angles[index]
        range_max = min(scan.range_max, cfg.laser_max_range)
        with np.errstate(invalid="ignore"):
            use = np.isfinite(ranges) & (ranges > scan.range_min) & (ranges < range_max)
        ranges, angles = ranges[use], angles[use]
        if len(ranges) == 0:
            return
        sensors = compose(self.particles, scan.sensor_offset)
        heading = sensors[:, 2:3] + angles[None, :]
        hits = np.stack(
            [
                sensors[:, 0:1] + ranges * np.cos(heading),
                sensors[:, 1:2] + ranges * np.sin(heading),
            ],
            axis=-1,
        )
        d = self._field.lookup(hits)
        pz = cfg.z_hit * np.exp(-(d * d) / (2.0 * cfg.sigma_hit**2)) + cfg.z_rand / range_max
        self.weights = self.weights * (1.0 + np.sum(pz**3, axis=1))
        self.weights /= self.weights.sum()

    def _resample(self) -> None:
        cfg = self.config
        cumulative = np.cumsum(self.weights)
        cumulative[-1] = 1.0
        n = cfg.max_particles
        draws = (self._rng.random() + np.arange(n)) / n
        picked = self.particles[np.searchsorted(cumulative, draws)]
        picked = picked[self._rng.permutation(n)]
        # KLD: keep drawing until the count exceeds the limit for the bins occupied so far.
        keys = np.floor(picked / _BIN).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        new_bin = np.zeros(n, dtype=np.int64)
        new_bin[first] = 1
        occupied = np.cumsum(new_bin)
        limits = kld_limit(occupied, cfg)
        enough = np.flatnonzero(np.arange(1, n + 1) > limits)
        keep = int(enough[0]) + 1 if len(enough) else n
        keep = min(max(keep, cfg.min_particles), n)
        self.particles = picked[:keep].copy()
        self.weights = np.full(keep, 1.0 / keep)

    def _cluster_mean(self) -> FloatArray:
        p, w = self.particles, self.weights
        keys = np.floor(p / _BIN).astype(np.int64)
        keys -= keys.min(axis=0) - 1
        grid = np.zeros(tuple(keys.max(axis=0) + 2), dtype=bool)
        grid[keys[:, 0], keys[:, 1], keys[:, 2]] = True
        labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
        of = labels[keys[:, 0], keys[:, 1], keys[:, 2]]
        totals = np.bincount(of, weights=w, minlength=count + 1)
        best = of == int(np.argmax(totals))
        wb = w[best] / w[best].sum()
        x, y = float(wb @ p[best, 0]), float(wb @ p[best, 1])
        theta = math.atan2(float(wb @ np.sin(p[best, 2])), float(wb @ np.cos(p[best, 2])))
        return np.array([x, y, theta])
