"""Writing benchmark sections into ``BENCHMARKS.md`` between markers, leaving the rest intact."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

HEADER = (
    "# Benchmarks\n\n"
    "Every figure below was produced by the command written above its table, on the machine\n"
    "named there, in one run. Machines here are shared and noisy: read medians and ratios.\n"
)


def replace_section(path: Path, name: str, body: str) -> None:
    """Replace (or append) the section ``name`` of a Markdown file.

    Args:
        path: the file; created with a header when missing.
        name: section id, used in the begin/end markers.
        body: Markdown text of the section.
    """
    begin = f"<!-- begin {name} -->"
    end = f"<!-- end {name} -->"
    text = path.read_text(encoding="utf-8") if path.exists() else HEADER
    block = f"{begin}\n{body.rstrip()}\n{end}"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = head + block + tail
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text, encoding="utf-8")


def positive_ints(text: str) -> list[int]:
    """An argparse type: comma-separated whole numbers, each at least 1 (``"50,100"``).

    Raises:
        argparse.ArgumentTypeError: anything else, saying what was expected.
    """
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give whole numbers separated by commas, e.g. 50,100"
        ) from None
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: every number must be at least 1")
    return values


def ints_text(least: int, empty: bool = False) -> Callable[[str], str]:
    """An argparse type for a benchmark that echoes its argument in its command line: the text
    itself, once every comma-separated part is a whole number of at least ``least`` (empty parts
    are skipped; ``empty``: no number at all is allowed too).
    """

    def check(text: str) -> str:
        parts = [part for part in text.split(",") if part.strip()]
        try:
            values = [int(part) for part in parts]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: give whole numbers separated by commas, e.g. 1,2"
            ) from None
        if not values and not empty:
            raise argparse.ArgumentTypeError(f"{text!r}: give at least one number")
        if any(v < least for v in values):
            raise argparse.ArgumentTypeError(f"{text!r}: every number must be at least {least}")
        return text

    return check


def positive_float(text: str) -> float:
    """An argparse type: a finite number over 0 (a duration, seconds).

    Raises:
        argparse.ArgumentTypeError: anything else.
    """
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give a number, e.g. 20") from None
    if not 0.0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"{text!r}: must be over 0")
    return value


def section_main(
    parser: argparse.ArgumentParser,
    render: Callable[[argparse.Namespace], str],
    section: str | Callable[[argparse.Namespace], str],
    argv: list[str] | None = None,
) -> int:
    """The command-line tail of a benchmark that writes one section of ``BENCHMARKS.md``.

    Adds ``--write`` to ``parser``, parses ``argv``, prints the section ``render`` returns for
    the parsed arguments and, with ``--write``, replaces the section ``section`` of
    ``BENCHMARKS.md`` in the working directory with it (``section`` may depend on the
    arguments: a callable of them).

    Returns:
        The exit code, 0.
    """
    parser.add_argument("--write", action="store_true", help="update BENCHMARKS.md")
    args = parser.parse_args(argv)
    text = render(args)
    print(text)
    if args.write:
        name = section if isinstance(section, str) else section(args)
        replace_section(Path("BENCHMARKS.md"), name, text)
    return 0
