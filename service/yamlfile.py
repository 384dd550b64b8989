"""YAML read from a file (a map_server map's YAML, a settings file): bounded whatever it holds.

A YAML document can name a value (an anchor) and repeat it (an alias) without copying it: a
few hundred bytes that nest a list of nine in itself ten times over ("billion laughs") load
in a millisecond as a handful of shared lists, and then any code that walks or prints the
value (an error message's ``repr``, a settings library's deep copy) meets billions of items:
``rlutf map import`` and ``rlutf config --settings`` ran for minutes and past 5 GB. A settings
or map file needs a few dozen values; :func:`load_yaml` counts them, every alias's anew, and
refuses a document past :data:`MAX_VALUES`.
"""

from __future__ import annotations

from typing import Any, Final

import yaml

#: Values a document may hold, counting each alias as the values it repeats.
MAX_VALUES: Final = 100_000


class YamlTooLarge(ValueError):
    """A YAML document that holds (or repeats, through its aliases) too many values."""


def load_yaml(text: str | bytes) -> Any:
    """``yaml.safe_load(text)``, refused past :data:`MAX_VALUES` values.

    Raises:
        yaml.YAMLError: not YAML.
        YamlTooLarge: more values than :data:`MAX_VALUES`, aliases counted as what they repeat.
    """
    try:
        doc = yaml.safe_load(text)
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
