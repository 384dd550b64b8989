import math

import numpy as np

from rlutf.search import RandomSearch


def _search(seed: int, delta: float = 0.2, delta_theta: float = 0.05) -> RandomSearch:
    return RandomSearch(
        np.random.default_rng(seed),
        np.array([1.0, -2.0, 0.5]),
        delta,
        delta_theta,
        candidates=5,
        max_rounds=6,
        delta_min=0.01,
        delta_theta_min=0.001,
        epsilon=0.0,
        elitist=True,
    )


def test_candidates_use_the_draws_and_radii_of_each_round() -> None:
    # The offsets of all rounds are made up front; they must equal drawing per round.
    search = _search(4)
    u = np.random.default_rng(4).random((5, 5, 3))
    steps = np.sqrt(u[..., 0]) * np.exp(2j * math.pi * u[..., 1])
    turns = 2.0 * u[..., 2] - 1.0
    best = search.best
    delta, delta_theta = 0.2, 0.05
    rounds = 0
    while rounds < 5:
        got = search.candidates()
        want = np.empty((5, 3))
        want[:, :2] = (steps[rounds] * delta).view(np.float64).reshape(5, 2) + best[:2]
        want[:, 2] = turns[rounds] * delta_theta + best[2]
        np.testing.assert_array_equal(got, want)
        # What one round of run() does when the second candidate wins.
        search.best, best = got[1], got[1]
        search.rounds += 1
        delta *= 0.5
        delta_theta *= 0.5
        rounds += 1


def test_run_consumes_rounds_until_the_radii_are_small() -> None:
    search = _search(7, delta=0.04, delta_theta=0.004)
    # 0.04 -> 0.02 -> 0.01 -> 0.005: three rounds open (delta >= 0.01 or dtheta >= 0.001).
    scored = search.run(lambda c: np.hypot(c[:, 0] - 1.0, c[:, 1] + 2.0))
    assert search.rounds == 3
    assert scored == 15


def test_no_rounds_planned_when_the_radii_start_small() -> None:
    search = _search(1, delta=0.001, delta_theta=0.0001)
    assert search.run(lambda c: np.zeros(len(c))) == 0
    assert search.rounds == 0
