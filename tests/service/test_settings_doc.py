"""docs/settings.md lists every setting of the service with its default: none missing, none
that no longer exists, and each default as the code has it."""

from __future__ import annotations

import dataclasses
import json
import re
import typing
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from service.config import Settings

PAGE = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
#: A table row: ``| `name` | default | what |``.
ROW = re.compile(r"^\| `([a-z0-9_.<>]+)` \| ([^|]+) \|", re.M)


def _flatten(model: type[BaseModel], prefix: str) -> dict[str, tuple[Any, str]]:
    """Every setting of a model by its dotted name, with its default and description: nested
    models (and dataclasses, and maps of models keyed by a name, ``<ns>``) give their own."""
    out: dict[str, tuple[Any, str]] = {}
    for name, field in model.model_fields.items():
        kind, args = field.annotation, typing.get_args(field.annotation)
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            out |= _flatten(kind, f"{prefix}{name}.")
        elif isinstance(kind, type) and dataclasses.is_dataclass(kind):
            for inner in dataclasses.fields(kind):
                out[f"{prefix}{name}.{inner.name}"] = (inner.default, "")
        elif len(args) == 2 and isinstance(args[1], type) and issubclass(args[1], BaseModel):
            out |= _flatten(args[1], f"{prefix}{name}.<ns>.")
        else:
            value = field.get_default(call_default_factory=True)
            value = str(value) if isinstance(value, Path) else value
            out[prefix + name] = (value, field.description or "")
    return out


def _code() -> dict[str, tuple[Any, str]]:
    """Every setting by its dotted name, with its default."""
    return _flatten(Settings, "")


def _page() -> dict[str, str]:
    return dict(ROW.findall(PAGE.read_text(encoding="utf-8")))


def _row(name: str, default: Any, description: str) -> str:
    """The table row of a setting, as the page writes it."""
    escaped = description.replace("|", r"\|")
    return f"| `{name}` | `{json.dumps(default)}` | {escaped} |"


def test_the_page_lists_every_setting_and_no_other() -> None:
    code, page = _code(), set(_page())
    rows = [_row(name, *code[name]) for name in sorted(set(code) - page)]
    assert not rows, "settings missing from docs/settings.md, add rows:\n" + "\n".join(rows)
    assert not page - set(code), f"docs/settings.md lists unknown settings: {page - set(code)}"


def test_the_defaults_on_the_page_are_the_code_s() -> None:
    code = _code()
    wrong = []
    for name, text in _page().items():
        cell = text.strip()
        if not cell.startswith("`"):
            continue  # said in words: it depends on the host or another setting
        if json.loads(cell.strip("`")) != code[name][0]:
            wrong.append(f"{name}: page {cell}, code {code[name][0]!r}")
    assert not wrong, "\n".join(wrong)
