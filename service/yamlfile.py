"""YAML read from a file (a map_server map's YAML, a settings file): bounded whatever it holds.

A YAML document can name a value (an anchor) and repeat it (an alias) without copying it: a
few hundred bytes that nest a list of nine in itself ten times over ("billion laughs") load
in a millisecond as a handful of shared lists, and then any code that walks or prints the
value (an error message's ``repr``, a settings library's deep copy) meets billions of items:
``rlutf map import`` and ``rlutf config --settings`` ran for minutes and past 5 GB. A settings
or map file needs a few dozen values; :func:`load_yaml` counts them, every alias's anew, and
refuses a document past :data:`MAX_VALUES`.

A settings file is read with ``unique=True`` (and its JSON with :func:`unique_keys`): a key
given twice in one mapping is refused with its line, as TOML's reader does, instead of the
second silently winning (``record_dir`` set at the top of a long file and again at its end).
"""

from __future__ import annotations

import json
import re
from typing import Any, Final

import yaml

#: The most of a settings file that is read (settings are a few kB; a larger file is refused
#: before it is read whole).
SETTINGS_MAX_BYTES: Final = 16 << 20
#: Values a document may hold, counting each alias as the values it repeats.
MAX_VALUES: Final = 100_000


class YamlTooLarge(ValueError):
    """A YAML document that holds (or repeats, through its aliases) too many values."""


class _UniqueLoader(yaml.SafeLoader):  # type: ignore[misc]
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (merges, ``<<``, may
    override as YAML says)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                again = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key: SafeLoader refuses it itself
                continue
            if again:
                raise yaml.constructor.ConstructorError(
                    None, None, f"found {key!r} twice in one mapping", key_node.start_mark
                )
        mapping: dict[Any, Any] = super().construct_mapping(node, deep)
        return mapping


def unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook`` of ``json.loads`` that refuses a key given twice in one object."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"found {key!r} twice in one object")
        out[key] = value
    return out


def load_yaml(text: str | bytes, unique: bool = False) -> Any:
    """``yaml.safe_load(text)``, refused past :data:`MAX_VALUES` values.

    Args:
        text: the document.
        unique: refuse a key given twice in one mapping (a settings file).

    Raises:
        yaml.YAMLError: not YAML (or, with ``unique``, a key twice).
        YamlTooLarge: more values than :data:`MAX_VALUES`, aliases counted as what they repeat.
    """
    try:
        doc = yaml.load(text, Loader=_UniqueLoader) if unique else yaml.safe_load(text)
    except RecursionError:
        raise YamlTooLarge("the document nests deeper than the YAML reader can follow") from None
    left = MAX_VALUES
    stack = [doc]
    while stack:
        value = stack.pop()
        left -= 1
        if left < 0:
            raise YamlTooLarge(
                f"the document holds more than {MAX_VALUES:,} values (counting what its "
                "aliases repeat): not a settings or map file"
            )
        if isinstance(value, dict):
            stack.extend(value.keys())
            stack.extend(value.values())
        elif isinstance(value, list):
            stack.extend(value)
    return doc


def where(err: BaseException) -> str:
    """``, line N`` of a JSON, TOML or YAML parser's error, where the parser says."""
    if isinstance(err, json.JSONDecodeError):
        return f", line {err.lineno}"
    mark = getattr(err, "problem_mark", None)  # yaml's MarkedYAMLError
    if mark is not None:
        return f", line {mark.line + 1}"
    found = re.search(r"line (\d+)", str(err))  # tomllib: "... (at line 3, column 5)"
    if found:
        return f", line {found.group(1)}"
    return ", at its end" if "end of document" in str(err) else ""


def problem(err: BaseException) -> str:
    """What a JSON, TOML or YAML parser (or the read before it) found wrong, in a phrase."""
    if isinstance(err, json.JSONDecodeError):
        return err.msg
    problem = getattr(err, "problem", None)  # yaml
    if problem:
        return str(problem)
    if isinstance(err, UnicodeDecodeError):
        return "not UTF-8 text"
    if isinstance(err, OSError):
        return err.strerror or str(err)
    return re.sub(r"\s*\(at (line \d+, column \d+|end of document)\)", "", str(err).splitlines()[0])
