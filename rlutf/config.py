"""Every parameter of the localizer, with its unit, and the presets.

:class:`LocalizerConfig` is a frozen dataclass of scalars (the service reads it from its
settings, nested under ``localizer``); :meth:`LocalizerConfig.paper` and
:meth:`LocalizerConfig.paper_area` are the paper's Algorithm 1 read literally.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

from rlutf.errors import ConfigError
from rlutf.refine import RefineSettings

Mode = Literal["default", "paper"]
DiscrepancyKind = Literal["turning", "area", "combined"]
Status = Literal["tracking", "corrected", "lost"]

#: ``(epsilon, lost_threshold)`` of each discrepancy in its own unit, for the default mode.
#: Measured on the simulated scenarios at the true pose and at poses 2, 5, 10 and 30 cm off:
#: the capped area (metres) is 0.002 at the truth, 0.012 at 5 cm (where the refinement's basin
#: still holds) and saturates near 0.03; the anchored turning distance (radians) is 0.2 at the
#: truth with a long tail (0.8 at the 90th percentile), 0.7 at 2 cm and 1.2 to 1.6 beyond.
THRESHOLDS: dict[str, tuple[float, float]] = {
    "area": (0.012, 0.03),
    "turning": (0.3, 1.2),
    "combined": (0.35, 1.5),
}
#: ``epsilon`` of the default mode without ``refine``: the search must then reach the bottom of
#: the basin itself, so it accepts only a near-noise-free fit (version 0.1's default).
SEARCH_ONLY_EPSILON: dict[str, float] = {"area": 0.0015, "turning": 0.3, "combined": 0.35}
#: The same for ``mode="paper"`` (perimeter-normalised turning functions, exact area): the
#: exact area is 0.002 at the truth and 0.03 at 2 cm; the normalised turning distance 0.19 and
#: 0.84.
PAPER_THRESHOLDS: dict[str, tuple[float, float]] = {
    "area": (0.005, 0.1),
    "turning": (0.25, 1.0),
    "combined": (0.3, 1.3),
}


@dataclass(frozen=True)
class LocalizerConfig:
    """Every parameter of the localizer, with its unit.

    Attributes:
        mode: ``"default"`` or ``"paper"`` (Algorithm 1 read literally: perimeter-normalised
            turning functions, no elitism, fixed initial radius, exact area, no refinement).
        discrepancy: ``"turning"`` (anchored turning function, radians), ``"area"`` (area between
            the polygons over the perimeter, metres) or ``"combined"`` (turning plus
            ``area_weight`` times area).
        epsilon: accept a pose whose discrepancy is under this (the discrepancy's unit);
            ``None``: the discrepancy's own default (:data:`THRESHOLDS`; without ``refine``,
            :data:`SEARCH_ONLY_EPSILON`).
        lost_threshold: a search stage ending over this searches again with the full radii
            (the discrepancy's unit); ``None``: the discrepancy's own default.
        candidates: random candidates per search round (the paper uses 3).
        delta: initial search radius in position, metres.
        delta_theta: initial search radius in heading, radians.
        delta_min: the search stops when the position radius falls under this, metres.
        delta_theta_min: ... and (default mode) the heading radius under this, radians.
        max_rounds: most search rounds per update.
        adaptive: start the search with radii from the odometry motion and the previous
            correction (default mode only), and search again with larger radii when a stage ends
            over ``lost_threshold`` (the full radii) or at the edge of its radii (doubled).
        delta_start: smallest adaptive position radius, metres.
        delta_per_metre: adaptive position radius per metre travelled.
        delta_theta_start: smallest adaptive heading radius, radians.
        delta_theta_per_radian: adaptive heading radius per radian turned.
        delta_theta_per_metre: adaptive heading radius per metre travelled, radians.
        delta_per_correction: adaptive radii grow by this times the previous update's correction
            (position and heading).
        expand_fraction: (adaptive) when a stage's best pose moved more than this fraction of its
            position or heading radius, another stage searches around it with the radii doubled.
        surprise_ratio: (adaptive) a stage that ends over this many times the running typical
            discrepancy (or over ``lost_threshold``) is followed by one with the full radii.
        typical_rate: weight of each update's discrepancy in the running typical one.
        max_stages: (adaptive) most search stages per update.
        area_cap: with ``discrepancy="area"``, each beam's share of the area is capped at a band
            of this width, metres (see :class:`rlutf.discrepancy.PolarArea`), or of the round's
            position radius times ``cap_per_radius`` if wider; ``None`` uses the exact area.
            ``"combined"`` always uses the exact area.
        cap_per_radius: (default mode) the cap is at least this times the round's position
            radius, so that the early, wide rounds of a search see beams that are far off.
        simplify_tolerance: Douglas-Peucker tolerance for the real polygon, metres (about two
            to three times the range noise).
        area_weight: weight of the area term in ``"combined"``, radians per metre.
        max_gap: widest angular gap between returns bridged by a polygon edge, radians; past
            it the polygon closes through the sensor.
        min_returns: fewer returns than this give status ``lost`` without a comparison.
        refine: refine the search's result by robust least squares on the ranges
            (:mod:`rlutf.refine`).
        coarse_tolerance: (with ``refine``, default mode) on a map traced from a grid, the
            acceptance test, the search and a first refinement run on the map's walls
            simplified at this tolerance, metres (:func:`rlutf.map.coarse_map`), and the answer
            is the refinement on the map itself from that pose or from the prediction, whichever
            explains the scan better. Traced walls run in steps and bumps of about a cell, where
            a refinement started a few centimetres off stops in small local minima; the
            simplified walls have fewer. A drawn map (one that barely simplifies) is tracked on
            directly. 0: always on the map.
        refine_iterations: most casts of the scan per refinement.
        refine_tolerance: a refinement step shorter than this, metres, that also turns less
            than ``refine_heading_tolerance`` is taken without casting the scan again, and ends
            the refinement (the step's error is of second order in its length).
        refine_heading_tolerance: the same bound on the step's turn, radians.
        noise_min: smallest range noise the refinement assumes, metres.
        noise_max: largest range noise the refinement assumes, metres.
        max_incidence: the refinement leaves out beams hitting a wall more obliquely than this,
            radians from the wall's normal.
        fit_distance: a beam fits the map when its measured range is within this of the range
            cast from the pose, metres.
        min_fit: status ``lost`` when fewer than this share of the returns fit ...
        fit_margin: ... or when the share falls more than this under the robot's running typical
            share (of its updates that were not lost): a pose that fits the scan far worse than
            this robot's poses usually do is not to be trusted (after a kidnapping, the best
            pose near the old one may still fit half of the beams).
        fit_deviations: ... the margin is this many times the robot's running mean deviation of
            the share from its typical share, between 0.05 and ``fit_margin``: a simulated scan
            fits within a point of its typical share, a real log's within several, so a fall
            of 20 points means little on one and everything on the other.
        probation_margin: after a ``lost`` update, the updates stay ``lost`` until one fits
            within this of the typical share again: a robot that lost its place and found one
            that fits a little worse than usual (a room like its own) has not found its place.
        wide_search: search a wide region on the distance field when the pose is uncertain:
            the first update, after :meth:`Localizer.reset`, after a ``lost`` update, and when
            the prediction does not fit (default mode only).
        spread: how far off (metres) a pose given without its own spread may be: an
            operator's click on a map.
        spread_heading: the same for the heading, radians.
        wide_step: position step of the wide search's grid, metres.
        wide_cap: the wide search's per-point cap, metres.
        wide_keep: poses of the wide search refined and compared.
        select_scale: scale of the Cauchy cost that compares refined candidates, metres (about
            three times a good scanner's range noise: fine enough to tell two nearby basins
            apart, coarse enough that map errors do not decide).
        relocalize_after: after this many ``lost`` updates in a row the localizer relocalizes
            by itself (:meth:`Localizer.relocalize` on the whole map); 0 never. A relocalization
            in a circle (an operator's ``--near``) with no answer after this many scans searches
            the whole map from then on.
        relocalize_resolution: cell side of the relocalization's search grid, metres.
        seed_fit: the first update after a seeded pose (an initial pose, a handover, a
            restart) must fit at least this share of the scan's returns, or the update is
            ``lost`` and the robot is relocalized at once (default mode, with
            ``relocalize_after`` > 0): a seed is a claim, not a fact. 0: not checked.
        relocalize_fit: a relocalization's answer must fit at least this share of the scan's
            returns (within ``fit_distance``) to be taken; and the first scan's answer only
            if no other distinct pose fits within 5 points of it.
        follow_scans: scans an ambiguous relocalization follows its hypotheses before it
            searches the map again.
        win_margin: a followed hypothesis wins when its summed unfit share over the scans
            followed is at least this much under every other's.
        quality_range: the localization score of a pose halves when its deviation range (the
            95 % radius of its position) reaches this, metres (:mod:`rlutf.quality`).
        seed: base seed of the random generator.
    """

    mode: Mode = "default"
    discrepancy: DiscrepancyKind = "area"
    epsilon: float | None = None
    lost_threshold: float | None = None
    candidates: int = 8
    delta: float = 0.3
    delta_theta: float = 0.12
    delta_min: float = 0.003
    delta_theta_min: float = 0.001
    max_rounds: int = 10
    adaptive: bool = True
    delta_start: float = 0.004
    delta_per_metre: float = 0.05
    delta_theta_start: float = 0.002
    delta_theta_per_radian: float = 0.05
    delta_theta_per_metre: float = 0.02
    delta_per_correction: float = 1.0
    expand_fraction: float = 0.75
    surprise_ratio: float = 1.6
    typical_rate: float = 0.1
    max_stages: int = 4
    area_cap: float | None = 0.1
    cap_per_radius: float = 1.0
    simplify_tolerance: float = 0.03
    area_weight: float = 5.0
    max_gap: float = 0.35
    min_returns: int = 8
    refine: bool = True
    coarse_tolerance: float = 0.07
    refine_iterations: int = 12
    refine_tolerance: float = 1e-3
    refine_heading_tolerance: float = 3e-4
    noise_min: float = 0.002
    noise_max: float = 0.2
    max_incidence: float = math.radians(80.0)
    fit_distance: float = 0.1
    min_fit: float = 0.5
    fit_margin: float = 0.25
    fit_deviations: float = 8.0
    probation_margin: float = 0.1
    wide_search: bool = True
    spread: float = 0.5
    spread_heading: float = math.radians(15.0)
    wide_step: float = 0.1
    wide_cap: float = 0.3
    wide_keep: int = 6
    select_scale: float = 0.03
    relocalize_after: int = 5
    relocalize_resolution: float = 0.1
    relocalize_fit: float = 0.8
    seed_fit: float = 0.8
    follow_scans: int = 10
    win_margin: float = 0.3
    quality_range: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in ("default", "paper"):
            raise ConfigError(f"mode: expected 'default' or 'paper', got {self.mode!r}")
        if self.discrepancy not in ("turning", "area", "combined"):
            raise ConfigError(f"discrepancy: unknown kind {self.discrepancy!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{f.name}: must be finite, got {value}")
        positive = (
            "delta",
            "delta_theta",
            "delta_min",
            "max_gap",
            "refine_tolerance",
            "refine_heading_tolerance",
            "noise_min",
            "noise_max",
            "max_incidence",
            "fit_distance",
            "spread",
            "spread_heading",
            "wide_step",
            "wide_cap",
            "select_scale",
            "relocalize_resolution",
            "win_margin",
            "quality_range",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("epsilon", "lost_threshold"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"{name}: must be positive or None, got {value}")
        non_negative = (
            "delta_theta_min",
            "delta_theta_per_metre",
            "expand_fraction",
            "surprise_ratio",
            "typical_rate",
            "delta_start",
            "delta_per_metre",
            "delta_theta_start",
            "delta_theta_per_radian",
            "delta_per_correction",
            "simplify_tolerance",
            "coarse_tolerance",
            "cap_per_radius",
            "fit_margin",
            "probation_margin",
            "fit_deviations",
        )
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.area_cap is not None and not self.area_cap > 0:
            raise ConfigError(f"area_cap: must be positive or None, got {self.area_cap}")
        if self.candidates < 1:
            raise ConfigError(f"candidates: must be at least 1, got {self.candidates}")
        if self.max_rounds < 0:
            raise ConfigError(f"max_rounds: must be at least 0, got {self.max_rounds}")
        if self.max_stages < 1:
            raise ConfigError(f"max_stages: must be at least 1, got {self.max_stages}")
        if self.refine_iterations < 1:
            raise ConfigError(
                f"refine_iterations: must be at least 1, got {self.refine_iterations}"
            )
        if self.relocalize_after < 0:
            raise ConfigError(f"relocalize_after: must be >= 0, got {self.relocalize_after}")
        if self.follow_scans < 1:
            raise ConfigError(f"follow_scans: must be at least 1, got {self.follow_scans}")
        if not 0.0 <= self.seed_fit <= 1.0:
            raise ConfigError(f"seed_fit: must be within [0, 1], got {self.seed_fit}")
        if not 0.0 < self.relocalize_fit <= 1.0:
            raise ConfigError(f"relocalize_fit: must be within (0, 1], got {self.relocalize_fit}")
        if self.wide_keep < 1:
            raise ConfigError(f"wide_keep: must be at least 1, got {self.wide_keep}")
        if not 0.0 <= self.min_fit <= 1.0:
            raise ConfigError(f"min_fit: must be within [0, 1], got {self.min_fit}")
        if self.noise_max < self.noise_min:
            raise ConfigError("noise_max: must be at least noise_min")
        if self.max_incidence >= math.pi / 2:
            raise ConfigError(f"max_incidence: must be under pi/2, got {self.max_incidence}")
        if self.lost_above < self.accept_below:
            raise ConfigError("lost_threshold: must be at least epsilon")

    @property
    def accept_below(self) -> float:
        """``epsilon``, or the discrepancy's own default."""
        if self.epsilon is not None:
            return self.epsilon
        if self.mode == "paper":
            return PAPER_THRESHOLDS[self.discrepancy][0]
        if not self.refine:
            return SEARCH_ONLY_EPSILON[self.discrepancy]
        return THRESHOLDS[self.discrepancy][0]

    @property
    def lost_above(self) -> float:
        """``lost_threshold``, or the discrepancy's own default."""
        table = PAPER_THRESHOLDS if self.mode == "paper" else THRESHOLDS
        return (
            self.lost_threshold if self.lost_threshold is not None else table[self.discrepancy][1]
        )

    @classmethod
    def paper(cls, **overrides: object) -> LocalizerConfig:
        """The paper's Algorithm 1 as literally as it can be read: step 4 compares the two
        polygons' turning functions (perimeter-normalised, the area between them), three random
        candidates per round, no elitism, no refinement."""
        base = cls(
            mode="paper",
            discrepancy="turning",
            adaptive=False,
            candidates=3,
            delta=0.04,
            delta_theta=0.03,
            delta_min=0.001,
            max_rounds=12,
            area_cap=None,
            refine=False,
            wide_search=False,
            relocalize_after=0,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]

    @classmethod
    def paper_area(cls, **overrides: object) -> LocalizerConfig:
        """:meth:`paper` with the area between the two polygons as its comparison (the paper
        preset of version 0.1)."""
        return cls.paper(discrepancy="area", **overrides)

    def refine_settings(self) -> RefineSettings:
        """The refinement's parameters."""
        return RefineSettings(
            iterations=self.refine_iterations,
            tolerance=self.refine_tolerance,
            heading_tolerance=self.refine_heading_tolerance,
            sigma_min=self.noise_min,
            sigma_max=self.noise_max,
            max_incidence=self.max_incidence,
        )
