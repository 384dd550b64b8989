"""Simulated buildings, trajectories, laser scans and drifting odometry, with ground truth.

Pure functions over a caller's :class:`numpy.random.Generator`, so the demo, the tests and the
benchmarks produce the same worlds and runs from the same seeds.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import LineString, Polygon, box

from rlutf.map import Map
from rlutf.motion import compose, relative, wrap_scalar
from rlutf.raycast import cast_rays
from rlutf.scan import Scan

FloatArray = NDArray[np.float64]


def make_building(
    rng: np.random.Generator,
    width: float = 24.0,
    height: float = 14.0,
    rooms_x: int = 3,
    rooms_y: int = 2,
    pillars: int = 6,
    shelves: int = 3,
) -> Map:
    """A floor with a grid of rooms joined by doors, plus pillars and shelves.

    Args:
        rng: random generator.
        width: outer width, metres.
        height: outer height, metres.
        rooms_x: rooms along x.
        rooms_y: rooms along y.
        pillars: square pillars (0.4 m) placed at random.
        shelves: shelves (2 m by 0.5 m) placed at random.

    Returns:
        The map; its free space is one connected polygon with holes.
    """
    outer = box(0.0, 0.0, width, height)
    walls = []
    wall_t = 0.15
    door = 1.0
    for i in range(1, rooms_x):
        x = width * i / rooms_x + rng.uniform(-0.5, 0.5)
        for j in range(rooms_y):
            y0, y1 = height * j / rooms_y, height * (j + 1) / rooms_y
            d = rng.uniform(y0 + 0.5, y1 - 0.5 - door)
            walls.append(box(x, y0, x + wall_t, d))
            walls.append(box(x, d + door, x + wall_t, y1))
    for j in range(1, rooms_y):
        y = height * j / rooms_y + rng.uniform(-0.4, 0.4)
        for i in range(rooms_x):
            x0, x1 = width * i / rooms_x, width * (i + 1) / rooms_x
            d = rng.uniform(x0 + 0.5, x1 - 0.5 - door)
            walls.append(box(x0, y, d, y + wall_t))
            walls.append(box(d + door, y, x1, y + wall_t))
    blocked = shapely.union_all(walls)
    obstacles = []
    for size_x, size_y, count in ((0.4, 0.4, pillars), (2.0, 0.5, shelves)):
        placed = 0
        for _ in range(50 * max(count, 1)):
            if placed >= count:
                break
            sx, sy = (size_x, size_y) if rng.random() < 0.5 else (size_y, size_x)
            x = rng.uniform(1.0, width - 1.0 - sx)
            y = rng.uniform(1.0, height - 1.0 - sy)
            ob = box(x, y, x + sx, y + sy)
            if ob.buffer(1.0).intersects(blocked):
                continue
            obstacles.append(ob)
            blocked = blocked.union(ob)
            placed += 1
    free = outer.difference(blocked)
    if not isinstance(free, Polygon):
        free = max(free.geoms, key=lambda g: g.area)
    return Map.from_shapely(shapely.set_precision(free, 1e-6))


def _inner(world: Map, clearance: float) -> shapely.Geometry:
    """The free space at least ``clearance`` metres from any wall, prepared; made once per map
    and clearance (on a map with thousands of obstacles the buffer takes seconds, and every
    robot, person and path drawn on it asks)."""

    def make(w: Map) -> shapely.Geometry:
        inner = w.geometry.buffer(-clearance)
        shapely.prepare(inner)
        return inner

    return world.derived(f"sim-inner:{clearance!r}", make)


def random_free_point(world: Map, rng: np.random.Generator, clearance: float = 0.5) -> FloatArray:
    """A uniformly drawn point of the free space at least ``clearance`` metres from any wall."""
    inner = _inner(world, clearance)
    if inner.is_empty:
        raise ValueError(f"no free space with clearance {clearance} m")
    minx, miny, maxx, maxy = inner.bounds
    for _ in range(10_000):
        p = rng.uniform((minx, miny), (maxx, maxy))
        if shapely.contains_xy(inner, float(p[0]), float(p[1])):
            return np.asarray(p, dtype=np.float64)
    raise ValueError("could not draw a free point")


def make_trajectory(
    world: Map,
    rng: np.random.Generator,
    steps: int,
    dt: float = 0.1,
    speed: float = 0.8,
    clearance: float = 0.45,
) -> FloatArray:
    """A smooth path through free space: straight legs between visible waypoints.

    Args:
        world: the map.
        rng: random generator.
        steps: number of poses.
        dt: time between poses, seconds.
        speed: forward speed, metres per second.
        clearance: smallest distance of the path from walls, metres.

    Returns:
        ``(steps, 3)`` poses; heading follows the direction of travel, turning at most
        ``2 rad/s``.
    """
    inner = _inner(world, clearance)
    pos = random_free_point(world, rng, clearance + 0.05)
    target = pos
    heading = rng.uniform(-math.pi, math.pi)
    out = np.empty((steps, 3))
    step = speed * dt
    max_turn = 2.0 * dt
    for i in range(steps):
        if np.hypot(*(target - pos)) <= step:
            target = _next_waypoint(inner, rng, pos, heading, target)
        want = math.atan2(target[1] - pos[1], target[0] - pos[0])
        turn = wrap_scalar(want - heading)
        heading = wrap_scalar(heading + max(-max_turn, min(max_turn, turn)))
        if abs(turn) < 0.5:
            move = pos + step * np.array([math.cos(heading), math.sin(heading)])
            # Moving along the heading (not the chord) bends the leg: the straight way from
            # the new position to the waypoint must still be clear, or the robot would stop at
            # a wall for good. A blocked move picks a new waypoint from here instead.
            if inner.contains(LineString([move, target])):
                pos = move
            else:
                target = _next_waypoint(inner, rng, pos, heading, pos)
        out[i] = (pos[0], pos[1], heading)
    return out


def _next_waypoint(
    inner: shapely.Geometry,
    rng: np.random.Generator,
    pos: FloatArray,
    heading: float,
    fallback: FloatArray,
    choices: int = 3,
) -> FloatArray:
    """A waypoint in straight view of ``pos`` within 6 m, at least 1 m off when possible.

    Of the first ``choices`` visible candidates the one needing the least turn wins, so the
    robot spends little time turning in place; ``fallback`` when none is found.
    """
    found: list[FloatArray] = []
    for _ in range(200):
        cand = pos + rng.uniform(-6.0, 6.0, 2)
        if np.hypot(*(cand - pos)) < 1.0 or not inner.contains(LineString([pos, cand])):
            continue
        found.append(cand)
        if len(found) >= choices:
            break
    if not found:
        return fallback
    turns = [abs(wrap_scalar(math.atan2(c[1] - pos[1], c[0] - pos[0]) - heading)) for c in found]
    return found[int(np.argmin(turns))]


@dataclass(frozen=True)
class LidarModel:
    """A 2D LiDAR.

    Attributes:
        beams: number of beams.
        fov: field of view, radians (2 pi for a full circle).
        max_range: metres.
        min_range: metres.
        noise: Gaussian range noise, one sigma, metres.
        dropout: probability that a beam reports no return.
    """

    beams: int = 360
    fov: float = 2.0 * math.pi
    max_range: float = 12.0
    min_range: float = 0.05
    noise: float = 0.01
    dropout: float = 0.0

    @property
    def angle_min(self) -> float:
        """Angle of the first beam, radians."""
        return -self.fov / 2.0 if self.fov < 2.0 * math.pi - 1e-9 else -math.pi

    @property
    def angle_increment(self) -> float:
        """Angle between beams, radians."""
        full = self.fov >= 2.0 * math.pi - 1e-9
        return self.fov / (self.beams if full else max(self.beams - 1, 1))


def simulate_scan(
    world: Map,
    pose: FloatArray,
    lidar: LidarModel,
    rng: np.random.Generator,
    people: FloatArray | None = None,
    person_radius: float = 0.25,
) -> Scan:
    """A noisy scan from ``pose`` (sensor at the robot base), with optional people as discs.

    Args:
        world: the map.
        pose: ``(3,)`` true pose.
        lidar: sensor model.
        rng: random generator.
        people: ``(P, 2)`` centres of people who are not on the map, metres.
        person_radius: metres.

    Returns:
        The scan with no-returns as NaN.
    """
    angles = lidar.angle_min + lidar.angle_increment * np.arange(lidar.beams)
    r = cast_rays(world, pose[None], angles, lidar.max_range)[0]
    if people is not None and len(people):
        r = np.minimum(
            r, _ray_discs(pose, np.asarray(angles, dtype=np.float64), people, person_radius)
        )
    r = r + rng.normal(0.0, lidar.noise, len(r)) if lidar.noise > 0 else r
    drop = rng.random(len(r)) < lidar.dropout
    r = np.where(drop | ~np.isfinite(r) | (r > lidar.max_range), np.nan, r)
    return Scan.create(r, lidar.angle_min, lidar.angle_increment, lidar.min_range, lidar.max_range)


def _ray_discs(
    pose: FloatArray, angles: FloatArray, centres: FloatArray, radius: float
) -> FloatArray:
    d = np.stack([np.cos(angles + pose[2]), np.sin(angles + pose[2])], axis=1)
    rel = centres - pose[:2]
    b = d @ rel.T
    c = np.sum(rel * rel, axis=1) - radius * radius
    disc = b * b - c
    t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    t = np.where(t > 0, t, np.inf)
    return np.asarray(t.min(axis=1), dtype=np.float64)


@dataclass(frozen=True)
class OdometryModel:
    """Wheel odometry that drifts.

    Attributes:
        trans_noise: relative noise on each step's translation (one sigma).
        rot_noise: relative noise on each step's rotation (one sigma).
        rot_per_metre: extra rotation noise per metre travelled, radians (one sigma).
        heading_bias: systematic heading error per metre travelled, radians.
    """

    trans_noise: float = 0.03
    rot_noise: float = 0.03
    rot_per_metre: float = 0.01
    heading_bias: float = 0.005


def drift_odometry(truth: FloatArray, model: OdometryModel, rng: np.random.Generator) -> FloatArray:
    """Odometry poses whose increments are the true increments plus noise and bias.

    Args:
        truth: ``(T, 3)`` true poses.
        model: noise model.
        rng: random generator.

    Returns:
        ``(T, 3)`` odometry poses in an odometry frame that starts at ``truth[0]``.
    """
    odom = np.empty_like(truth)
    odom[0] = truth[0]
    for i in range(1, len(truth)):
        d = relative(truth[i - 1], truth[i])
        dist = math.hypot(d[0], d[1])
        noisy = np.array(
            [
                d[0] * (1.0 + rng.normal(0.0, model.trans_noise)),
                d[1] * (1.0 + rng.normal(0.0, model.trans_noise)),
                d[2] * (1.0 + rng.normal(0.0, model.rot_noise))
                + rng.normal(0.0, model.rot_per_metre) * dist
                + model.heading_bias * dist,
            ]
        )
        odom[i] = compose(odom[i - 1], noisy)
    return odom


def people_walk(
    world: Map, rng: np.random.Generator, count: int, steps: int, dt: float = 0.1
) -> Iterator[FloatArray]:
    """Positions ``(count, 2)`` of people walking at 1 m/s, one array per step."""
    pos = np.array([random_free_point(world, rng, 0.3) for _ in range(count)]).reshape(-1, 2)
    vel = rng.normal(0.0, 1.0, (len(pos), 2))
    for _ in range(steps):
        nxt = pos + vel * dt
        inside = world.contains(nxt)
        vel[~inside] *= -1.0
        pos = np.where(inside[:, None], nxt, pos)
        yield pos.copy()
