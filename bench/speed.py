"""The speed benchmark: per-update latency against beams per scan and against map size.

Each point is one simulated run of the nominal scenario (changed only in the swept factor),
tracked by each method; the update latency's median and 99th percentile are reported. AMCL is
timed with a filter update on every scan (``update_min_d = update_min_a = -1``, so even a
robot standing still updates), once with its default 60 beams and once with every beam, so
that every method pays for the scan it is given.
The growth with the number of beams ``n`` is fitted as ``latency = a * n^b`` (log-log least
squares); the paper claims ``O(n log(delta/epsilon))``, i.e. ``b = 1``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from bench.accuracy import Profile, has_data
from bench.baselines import AmclConfig, ParticleFilter
from bench.measures import fit_power, rms
from bench.methods import Method, all_methods, track, warm_up
from bench.scenarios import Run, Scenario, imported_map, named_scenarios, simulate, with_beams
from rlutf.map import Map
from rlutf.sim import make_building

#: Methods of the sweeps, by name (see :func:`speed_methods`).
SPEED_METHODS = ("default", "norefine", "paper", "icp", "amcl-60", "amcl-all")


def speed_methods() -> list[Method]:
    """RLuTF default, without refinement and paper, ICP, and AMCL updating on every scan (60
    beams; all beams)."""
    by_name = {m.name: m for m in all_methods()}
    every = AmclConfig(update_min_d=-1.0, update_min_a=-1.0)
    every_all = replace(every, max_beams=100_000)
    prepare = by_name["amcl"].prepare
    return [
        *(by_name[n] for n in ("default", "norefine", "paper") if n in by_name),
        by_name["icp"],
        Method(
            "amcl-60",
            "AMCL, every scan, 60 beams",
            lambda w, p, s: ParticleFilter(w, p, every, seed=s),
            prepare,
        ),
        Method(
            "amcl-all",
            "AMCL, every scan, all beams",
            lambda w, p, s: ParticleFilter(w, p, every_all, seed=s),
            prepare,
        ),
    ]


@dataclass(frozen=True)
class Point:
    """One method at one setting.

    Attributes:
        method: method name.
        x: the swept value (beams, or walls in the map).
        label: the setting, for tables.
        median_ms: median update latency, milliseconds.
        p99_ms: 99th percentile, milliseconds.
        rmse: translation RMSE of the run, metres (a sanity check: fast but lost is no use).
    """

    method: str
    x: int
    label: str
    median_ms: float
    p99_ms: float
    rmse: float


def _measure(
    run: Run, methods: Sequence[Method], x: int, label: str, on_update: Callable[[], None] | None
) -> list[Point]:
    warm_up(methods, run)
    out = []
    for m in methods:
        t = track(m, run, seed=run.seed, on_update=on_update)
        ms = t.seconds * 1e3
        err = np.hypot(*(t.poses[:, :2] - run.truth[1:, :2]).T)
        out.append(
            Point(m.name, x, label, float(np.median(ms)), float(np.percentile(ms, 99)), rms(err))
        )
    return out


def _nominal(profile: Profile) -> Scenario:
    return replace(named_scenarios(profile.speed_updates + 1)[0], name="speed")


def latency_vs_beams(
    profile: Profile, methods: Sequence[Method], on_update: Callable[[], None] | None = None
) -> list[Point]:
    """Latency of each method on the nominal scenario with each beam count of the profile."""
    base = _nominal(profile)
    points = []
    for beams in profile.speed_beams:
        sc = with_beams(base, beams)
        points += _measure(simulate(sc, 1), methods, beams, f"{beams} beams", on_update)
    return points


def sweep_maps(profile: Profile) -> list[tuple[str, Map]]:
    """The maps of the map-size sweep: procedural buildings, then (full) imported and real."""
    maps = []
    for i, (w, h, rx, ry) in enumerate(profile.map_sizes):
        world = make_building(
            np.random.default_rng(100 + i), w, h, rx, ry, pillars=int(w * h / 50), shelves=rx * ry
        )
        maps.append((f"building {w:.0f} x {h:.0f} m", world))
    if profile.real_maps:
        from bench.carmen import carmen_world

        if has_data("depot"):
            maps.append(("depot (imported)", imported_map("depot")))
        maps += [
            (f"{n} (built from log)", carmen_world(n)) for n in ("intel", "aces") if has_data(n)
        ]
    return maps


def latency_vs_map(
    profile: Profile, methods: Sequence[Method], on_update: Callable[[], None] | None = None
) -> list[Point]:
    """Latency of each method, 360 beams, on maps of growing wall count."""
    base = _nominal(profile)
    points = []
    for label, world in sweep_maps(profile):
        run = simulate(base, 1, given=("sweep", world))
        points += _measure(run, methods, len(world.segments), label, on_update)
    return points


def growth(points: Sequence[Point]) -> dict[str, tuple[float, float]]:
    """Per method, the fitted ``(a, b)`` of ``median_ms = a * beams^b``."""
    out = {}
    for name in dict.fromkeys(p.method for p in points):
        pts = [p for p in points if p.method == name]
        if len(pts) >= 2:
            out[name] = fit_power(
                np.array([p.x for p in pts], dtype=np.float64),
                np.array([p.median_ms for p in pts]),
            )
    return out
