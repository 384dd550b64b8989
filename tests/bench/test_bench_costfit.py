"""The fit of the service's CPU per scan against the localizer's update (bench.costfit)."""

from __future__ import annotations

import math

import pytest

from bench.costfit import Point, fit_line, main, median_point, report, shares
from bench.floor import localizer_alone_ms


def test_the_line_through_exact_points_is_found() -> None:
    fixed, slope = fit_line([0.1, 0.2, 0.4], [0.5 + 1.5 * x for x in (0.1, 0.2, 0.4)])
    assert fixed == pytest.approx(0.5)
    assert slope == pytest.approx(1.5)


def test_the_line_through_noisy_points_is_the_least_squares_one() -> None:
    xs, ys = [0.0, 1.0, 2.0, 3.0], [1.0, 2.0, 2.0, 4.0]
    fixed, slope = fit_line(xs, ys)
    # Normal equations by hand: slope = sxy / sxx = 4.5 / 5, intercept = 2.25 - 0.9 * 1.5.
    assert slope == pytest.approx(0.9)
    assert fixed == pytest.approx(0.9)


@pytest.mark.parametrize(("xs", "ys"), [([1.0], [2.0]), ([1.0, 1.0], [2.0, 3.0])])
def test_no_line_from_one_point_or_one_update_time(xs: list[float], ys: list[float]) -> None:
    with pytest.raises(ValueError):
        fit_line(xs, ys)


def test_the_shares_split_a_scans_cost_two_ways() -> None:
    p = Point(beams=360, update_ms=0.2, service_ms=0.8, sent_ms=0.8, answered=1.0, p99_ms=20.0)
    fixed_share, beyond = shares(p, fixed=0.4)
    assert fixed_share == pytest.approx(0.5)
    assert beyond == pytest.approx(0.75)  # everything but the localizer's own 0.2 ms


def test_the_report_gives_the_line_and_each_beam_counts_shares() -> None:
    points = [
        Point(90, 0.1, 0.55, 0.56, 1.0, 12.0),
        Point(360, 0.2, 0.70, 0.70, 0.995, 20.0),
        Point(720, 0.4, 1.00, 1.01, 0.99, 30.0),
    ]
    text = report(points, robots=100, duration=20.0, load=0.1)
    assert "python -m bench.costfit --robots 100 --beams 90,360,720 --duration 20 --write" in text
    assert "**0.400 ms + 1.50 x the update**" in text
    row = next(line for line in text.splitlines() if line.startswith("| 360 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[6] == "0.700"  # the line at 0.2 ms: 0.4 + 1.5 x 0.2
    assert cells[7] == "57 %"  # 0.4 of 0.7
    assert cells[8] == "71 %"  # 1 - 0.2 / 0.7


def test_the_localizer_alone_costs_more_with_more_beams() -> None:
    # Four times the beams: every cast and every term of the refinement four times as long.
    few = localizer_alone_ms(180, robots=5, steps=160)
    many = localizer_alone_ms(720, robots=5, steps=160)
    assert math.isfinite(few) and few > 0.0
    assert many > few


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--beams", "360"], "two different beam counts"),
        (["--beams", "360,360"], "two different beam counts"),
        (["--beams", "90,x"], "whole numbers"),
        (["--beams", "0,90"], "at least 1"),
        (["--robots", "5,6"], "one whole number"),
        (["--rounds", "0"], "one whole number"),
        (["--duration", "0"], "must be over 0"),
    ],
)
def test_arguments_it_cannot_use_are_refused_before_anything_runs(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as ended:
        main(argv)
    assert ended.value.code == 2
    assert says in capsys.readouterr().err


def test_a_beam_counts_rounds_are_one_point_of_medians() -> None:
    runs = [
        Point(360, 0.18, 0.70, 0.69, 1.0, 25.0),
        Point(360, 0.17, 0.66, 0.66, 0.99, 40.0),
        Point(360, 0.20, 0.64, 0.64, 1.0, 22.0),
    ]
    p = median_point(runs)
    assert (p.beams, p.update_ms, p.service_ms, p.sent_ms) == (360, 0.18, 0.66, 0.66)
    assert (p.answered, p.p99_ms) == (1.0, 25.0)
    with pytest.raises(ValueError):
        median_point([runs[0], Point(90, 0.1, 0.5, 0.5, 1.0, 10.0)])


def test_the_command_names_its_rounds() -> None:
    points = [Point(90, 0.1, 0.55, 0.56, 1.0, 12.0), Point(360, 0.2, 0.70, 0.70, 1.0, 20.0)]
    text = report(points, robots=200, duration=20.0, load=0.1, rounds=3)
    assert "--beams 90,360 --duration 20 --rounds 3 --write" in text
    assert "3 rounds" in text
