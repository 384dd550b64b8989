"""The shared command-line tail of the benchmarks that write one section of BENCHMARKS.md."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from bench.report import ints_text, positive_float, positive_ints, section_main


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.example")
    parser.add_argument("--n", type=int, default=3)
    return parser


def test_prints_the_section_and_leaves_the_file_alone_without_write(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    assert section_main(_parser(), lambda a: f"n = {a.n}", "example", ["--n", "5"]) == 0
    assert capsys.readouterr().out == "n = 5\n"
    assert not (tmp_path / "BENCHMARKS.md").exists()


def test_write_replaces_only_its_section(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    other = "<!-- begin other -->\nkept\n<!-- end other -->"
    (tmp_path / "BENCHMARKS.md").write_text(
        f"# Benchmarks\n\n<!-- begin example -->\nold\n<!-- end example -->\n\n{other}\n"
    )
    section_main(_parser(), lambda a: f"n = {a.n}", "example", ["--write"])
    text = (tmp_path / "BENCHMARKS.md").read_text()
    assert "<!-- begin example -->\nn = 3\n<!-- end example -->" in text
    assert "old" not in text
    assert other in text


def test_lists_of_whole_numbers_are_checked_as_arguments() -> None:
    assert positive_ints("50,100") == [50, 100]
    assert ints_text(0)("0,2") == "0,2"  # echoed as given, in the command line
    assert ints_text(1, empty=True)("") == ""
    for bad in ("x", "50,", "0"):
        with pytest.raises(argparse.ArgumentTypeError):
            positive_ints(bad)
    for check, bad in ((ints_text(1), "0"), (ints_text(0), "1,b"), (ints_text(0), "")):
        with pytest.raises(argparse.ArgumentTypeError):
            check(bad)


def test_a_duration_must_be_a_number_over_zero() -> None:
    assert positive_float("2.5") == 2.5
    for bad in ("0", "-1", "inf", "nan", "soon"):
        with pytest.raises(argparse.ArgumentTypeError):
            positive_float(bad)
