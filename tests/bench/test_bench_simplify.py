"""The simplification benchmark's parts on a small cluttered site."""

import shapely

from bench import simplify as bench_simplify


def test_the_site_has_posts_and_walls() -> None:
    free = bench_simplify.site_grid(40)
    assert not free[0].any() and not free[:, -1].any()  # walls round it
    assert 0.7 < free[1:-1, 1:-1].mean() < 1.0  # and posts inside


def test_each_map_row_says_whether_both_ways_agree() -> None:
    site = shapely.geometry.box(0, 0, 2, 2).difference(shapely.geometry.box(0.5, 0.5, 0.6, 0.6))
    rows = bench_simplify.simplify_rows([("a room with a post", site)])
    assert len(rows) == len(bench_simplify.TOLERANCES)
    assert all(
        r.startswith("| a room with a post | 1 | 8 |") and r.endswith("| yes |") for r in rows
    )


def test_the_import_rows_compare_the_two_documents() -> None:
    rows = bench_simplify.import_rows(60)
    assert rows[0].startswith("| whole geometry |") and rows[1].startswith("| ring by ring |")
    assert rows[2] == "| the two Map JSON documents the same | yes | |"
