"""docs/settings.md lists every setting of the service with its default: none missing, none
that no longer exists, and each default as the code has it."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from rlutf.config import LocalizerConfig
from service.config import Ros2Robot, Ros2Settings, Settings

PAGE = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
#: A table row: ``| `name` | default | what |``.
ROW = re.compile(r"^\| `([a-z0-9_.<>]+)` \| ([^|]+) \|", re.M)


def _defaults(model: type[BaseModel], prefix: str, nested: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        if name not in nested:
            value = field.get_default(call_default_factory=True)
            out[prefix + name] = str(value) if isinstance(value, Path) else value
    return out


def _code() -> dict[str, Any]:
    """Every setting by its dotted name, with its default."""
    found = _defaults(Settings, "", ("ros2", "localizer"))
    found |= _defaults(Ros2Settings, "ros2.", ("robots",))
    found |= _defaults(Ros2Robot, "ros2.robots.<ns>.", ())
    for field in dataclasses.fields(LocalizerConfig):
        found[f"localizer.{field.name}"] = field.default
    return found


def _page() -> dict[str, str]:
    return dict(ROW.findall(PAGE.read_text(encoding="utf-8")))


def test_the_page_lists_every_setting_and_no_other() -> None:
    code, page = set(_code()), set(_page())
    assert not code - page, f"settings missing from docs/settings.md: {sorted(code - page)}"
    assert not page - code, f"docs/settings.md lists unknown settings: {sorted(page - code)}"


def test_the_defaults_on_the_page_are_the_code_s() -> None:
    code = _code()
    wrong = []
    for name, text in _page().items():
        cell = text.strip()
        if not cell.startswith("`"):
            continue  # said in words: it depends on the host or another setting
        if json.loads(cell.strip("`")) != code[name]:
            wrong.append(f"{name}: page {cell}, code {code[name]!r}")
    assert not wrong, "\n".join(wrong)
