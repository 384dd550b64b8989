"""Write or check the JSON Schema files of the wire messages.

Usage::

    python -m schemas.generate            # (re)write schemas/jsonschema/rlutf.*.json
    python -m schemas.generate --check    # exit 1, listing files that differ from the models

One file per entry of :data:`schemas.names.SCHEMA_NAMES`, named ``<schema name>.json``,
pretty-printed with sorted keys and a trailing newline, so diffs stay readable and a CI
check catches a model changed without regenerating.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Final

from schemas.names import SCHEMA_NAMES, json_schema

SCHEMA_DIR: Final = Path(__file__).resolve().parent / "jsonschema"
"""Where the checked-in schema files live."""

_GLOB: Final = "rlutf.*.json"


def render_schemas() -> dict[str, str]:
    """Render every schema file.

    Returns:
        File name (e.g. ``"rlutf.LaserScan.json"``) to its exact text.
    """
    return {
        f"{name}.json": json.dumps(json_schema(model), indent=2, sort_keys=True) + "\n"
        for model, name in SCHEMA_NAMES.items()
    }


def stale_files(directory: Path) -> list[str]:
    """List schema files in ``directory`` that are missing, differ, or belong to no model.

    Args:
        directory: The folder to compare, normally :data:`SCHEMA_DIR`.

    Returns:
        Sorted file names; empty when the folder matches the models exactly.
    """
    expected = render_schemas()
    found = {path.name for path in directory.glob(_GLOB)} if directory.is_dir() else set()
    wrong = {
        name
        for name, text in expected.items()
        if name not in found or (directory / name).read_text(encoding="utf-8") != text
    }
    return sorted(wrong | (found - expected.keys()))


def write_schemas(directory: Path) -> list[str]:
    """Write every schema file into ``directory`` and delete files no model produces.

    Files are only rewritten when their text changes.

    Args:
        directory: Target folder, created if missing.

    Returns:
        Sorted names of the files written or deleted.
    """
    directory.mkdir(parents=True, exist_ok=True)
    expected = render_schemas()
    changed = stale_files(directory)
    for name in changed:
        path = directory / name
        if name in expected:
            path.write_text(expected[name], encoding="utf-8", newline="\n")
        else:
            path.unlink()
    return changed


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line.

    Args:
        argv: Arguments without the program name; ``sys.argv[1:]`` if ``None``.

    Returns:
        The exit code: 0 when the files are (now) up to date, 1 when ``--check`` found a
        difference.
    """
    parser = argparse.ArgumentParser(
        prog="python -m schemas.generate", description=__doc__.splitlines()[0] if __doc__ else ""
    )
    parser.add_argument(
        "--check", action="store_true", help="only compare; exit 1 listing files that differ"
    )
    parser.add_argument(
        "--dir", type=Path, default=SCHEMA_DIR, help=f"schema folder (default {SCHEMA_DIR})"
    )
    args = parser.parse_args(argv)
    directory: Path = args.dir
    if args.check:
        differ = stale_files(directory)
        for name in differ:
            print(f"{directory / name}: out of date", file=sys.stderr)
        if differ:
            print("run: python -m schemas.generate", file=sys.stderr)
        return 1 if differ else 0
    for name in write_schemas(directory):
        print(f"updated {directory / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
