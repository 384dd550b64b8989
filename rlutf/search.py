"""The random search of RLuTF: rounds of random candidate poses around the best one so far.

Each round draws ``candidates`` poses uniformly in the disc of radius ``delta`` around the best
pose and within ``delta_theta`` of its heading, keeps the best of them (with ``elitist``, only if
it beats the current best), then halves both radii. The search stops when the best discrepancy
is under ``epsilon``, after ``max_rounds`` rounds, or when both radii are under their minimums.
Every candidate therefore lies within twice the initial radii of the start.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_TWO_PI_J = 2j * math.pi


class RandomSearch:
    """One search from ``start``; the random numbers of all its rounds are drawn up front.

    Args:
        rng: the generator to draw from.
        start: ``(3,)`` pose to search around.
        delta: initial position radius, metres.
        delta_theta: initial heading radius, radians.
        candidates: poses per round.
        max_rounds: most rounds.
        delta_min: the search stops once the position radius is under this, metres ...
        delta_theta_min: ... and the heading radius under this, radians (``inf``: ignore it).
        epsilon: the search stops once the best discrepancy is under this.
        elitist: keep the best so far unless a candidate beats it (``False``: the paper's
            procedure, which moves to the best candidate of every round).

    Attributes:
        best: ``(3,)`` best pose so far.
        best_d: its discrepancy (set it to the start's before :meth:`run`).
        rounds: rounds done.
        pending: candidates of the current round scored already, with their discrepancies;
            :meth:`run` uses them instead of drawing and scoring the round.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        start: FloatArray,
        delta: float,
        delta_theta: float,
        *,
        candidates: int,
        max_rounds: int,
        delta_min: float,
        delta_theta_min: float,
        epsilon: float,
        elitist: bool,
    ) -> None:
        self.best = start
        self.best_d = math.inf
        self.rounds = 0
        self._radii0 = (delta, delta_theta)
        self.pending: tuple[FloatArray, FloatArray] | None = None
        self._epsilon = epsilon
        self._elitist = elitist
        d, dt = delta, delta_theta
        radii: list[tuple[float, float, float]] = []
        while len(radii) < max_rounds and (d >= delta_min or dt >= delta_theta_min):
            radii.append((d, d, dt))
            d *= 0.5
            dt *= 0.5
        planned = len(radii)
        u = rng.random((planned, candidates, 3))
        steps = np.sqrt(u[..., 0]) * np.exp(_TWO_PI_J * u[..., 1])
        # Every round's offsets from its best pose, made at once: (dx, dy, dtheta) are the step
        # times the round's radius, the radii halved each round, so each round's candidates
        # cost one addition.
        offsets = np.empty((planned, candidates, 3))
        offsets[..., 0] = steps.real
        offsets[..., 1] = steps.imag
        np.multiply(u[..., 2], 2.0, out=offsets[..., 2])
        offsets[..., 2] -= 1.0
        offsets *= np.array(radii).reshape(planned, 1, 3)
        self._offsets = offsets

    @property
    def delta(self) -> float:
        """Position radius of the current round, metres (halved after every round)."""
        return self._radii0[0] * 0.5**self.rounds

    @property
    def delta_theta(self) -> float:
        """Heading radius of the current round, radians (halved after every round)."""
        return self._radii0[1] * 0.5**self.rounds

    def candidates(self) -> FloatArray:
        """``(candidates, 3)`` random poses of the current round around the best."""
        cand: FloatArray = self._offsets[self.rounds] + self.best
        return cand

    def run(self, score: Callable[[FloatArray], FloatArray]) -> int:
        """Search until a stop condition.

        Args:
            score: ``(K,)`` discrepancies of ``(K, 3)`` poses; ``inf`` for impossible ones.

        Returns:
            The number of poses scored.
        """
        scored = 0
        # The plan made at construction holds exactly the rounds whose radii are still open.
        while self.rounds < len(self._offsets) and self.best_d >= self._epsilon:
            if self.pending is not None:
                cand, d = self.pending
                self.pending = None
            else:
                cand = self.candidates()
                d = score(cand)
                scored += len(cand)
            i = int(d.argmin())
            di = float(d[i])
            if math.isfinite(di) and (not self._elitist or di < self.best_d):
                self.best, self.best_d = cand[i], di
            self.rounds += 1
        return scored
