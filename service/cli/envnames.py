"""``RLUTF_*`` environment variables that name no setting.

pydantic-settings reads only the variables that name a setting and passes over the others in
silence, so a misspelt top-level one (``RLUTF_METRICS_PROT=9464`` in a Deployment) left the
setting at its default with no word, while a misspelt nested one
(``RLUTF_LOCALIZER__MIN_FTI``) is refused. ``rlutf serve`` and ``rlutf config`` name them,
with the setting meant where one is close, and go on (a warning: an environment may hold
variables of this prefix that are not settings).
"""

from __future__ import annotations

import difflib
import sys
from collections.abc import Iterable, Mapping

PREFIX = "RLUTF_"

# Read by rlutf, but not settings: the settings file, the image's health check, heap dumps.
NOT_SETTINGS = frozenset(
    {"RLUTF_SETTINGS", "RLUTF_HEALTH_ARGS", "RLUTF_TRACEMALLOC", "RLUTF_TRACEMALLOC_DIR"}
)


def unknown(environ: Mapping[str, str], settings: Iterable[str]) -> list[str]:
    """One line per ``RLUTF_*`` variable of ``environ`` that names none of ``settings``."""
    names = {s.upper() for s in settings}
    lines = []
    for var in sorted(environ):
        upper = var.upper()
        if not upper.startswith(PREFIX) or upper in NOT_SETTINGS:
            continue
        head = upper[len(PREFIX) :].split("__", 1)[0]  # RLUTF_LOCALIZER__EPSILON: localizer
        if head in names:
            continue
        close = difflib.get_close_matches(head, sorted(names), n=1)
        hint = f"; did you mean {PREFIX}{close[0]}?" if close else ""
        lines.append(f"{var} in the environment names no setting: ignored{hint}")
    return lines


def warn_unknown(command: str, environ: Mapping[str, str]) -> None:
    """Print :func:`unknown`'s lines for ``command`` on stderr."""
    from service.config import Settings

    for line in unknown(environ, Settings.model_fields):
        print(
            f"{command}: warning: {line} (`rlutf config` prints the settings in effect)",
            file=sys.stderr,
        )
