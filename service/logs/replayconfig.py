"""The configuration a replay runs with: the log's ``rlutf.config``, then overrides.

The recorded configuration (``rlutf.config`` metadata, the output of ``rlutf config``) is the
base; a settings file given with ``--settings`` (JSON, TOML or YAML, same structure) is merged
into it key by key, then each ``--set KEY=VALUE`` (dotted keys, e.g.
``--set localizer.epsilon=0.004``; the value is read as JSON, else taken as text). A log with no
configuration replays on the defaults, with the key prefix read from its topics. The
environment (``RLUTF_*``) is never read: a replay depends on its inputs and flags only.
"""

from __future__ import annotations

import copy
import json
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, TypeVar

from pydantic import TypeAdapter, ValidationError

from rlutf.localizer import LocalizerConfig
from rlutf.map import MapLimits
from service.config import Settings
from service.guard import Limits
from service.infile import read_regular
from service.yamlfile import SETTINGS_MAX_BYTES

_DEFAULT_LIMITS = MapLimits(
    Settings.model_fields["max_map_area"].default,
    Settings.model_fields["max_map_vertices"].default,
)


class ReplayConfigError(ValueError):
    """A configuration a replay cannot run with; the message names the key."""


@dataclass(frozen=True)
class ReplayConfig:
    """What the engine needs, plus the full configuration to store in the output.

    Attributes:
        prefix: key prefix of the outputs.
        localizer: localizer parameters.
        event_interval_ns: least time between two events of one code for one robot.
        max_payload_bytes: largest accepted payload of a robot's message.
        settings: the merged configuration, stored as ``rlutf.config`` in the output.
        limits: what inputs may hold beyond the schema.
        max_map_bytes: largest accepted Map payload (the live service's ``max_map_bytes``).
        map_limits: extent and vertex limits of a map, as live, so that an audit reproduces
            which maps were refused.
    """

    prefix: str
    localizer: LocalizerConfig
    event_interval_ns: int
    max_payload_bytes: int
    settings: dict[str, Any]
    limits: Limits = field(default_factory=Limits)
    max_map_bytes: int = Settings.model_fields["max_map_bytes"].default
    map_limits: MapLimits = _DEFAULT_LIMITS


#: A number a setting is read as.
N = TypeVar("N", int, float)


def _default(name: str) -> Any:
    return Settings.model_fields[name].default


def default_settings(prefix: str | None) -> dict[str, Any]:
    """The parts of the service defaults a replay uses (no environment)."""
    return {
        "prefix": prefix or _default("prefix"),
        "event_interval_s": _default("event_interval_s"),
        "max_payload_bytes": _default("max_payload_bytes"),
        "max_map_bytes": _default("max_map_bytes"),
        "max_map_area": _default("max_map_area"),
        "max_map_vertices": _default("max_map_vertices"),
        "localizer": asdict(LocalizerConfig()),
        "limits": Limits().model_dump(mode="json"),
    }


def _merge(base: dict[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = copy.deepcopy(value)
    return base


def read_settings_file(path: Path) -> dict[str, Any]:
    """A settings file as a mapping (JSON, TOML or YAML, by suffix)."""
    try:
        text = read_regular(path, SETTINGS_MAX_BYTES).decode("utf-8")
    except OSError as err:
        raise ReplayConfigError(f"cannot read settings file {path}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise ReplayConfigError(
            f"settings file {path}: not UTF-8 text (byte {err.start}); give a JSON, TOML or "
            "YAML file"
        ) from err
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            data = json.loads(text)
        elif suffix == ".toml":
            data = tomllib.loads(text)
        elif suffix in (".yaml", ".yml"):
            from service.yamlfile import load_yaml

            data = load_yaml(text)
        else:
            raise ReplayConfigError(f"settings file {path}: use .json, .toml or .yaml")
    except (ValueError, RecursionError, ImportError) as err:
        if isinstance(err, ReplayConfigError):
            raise
        raise ReplayConfigError(f"settings file {path}: {err}") from err
    if not isinstance(data, dict):
        raise ReplayConfigError(f"settings file {path}: expected a mapping at the top")
    return data


def _assignment(text: str) -> dict[str, Any]:
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ReplayConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. localizer.epsilon=0.004")
    try:
        value: Any = json.loads(raw)
    except (json.JSONDecodeError, RecursionError):
        value = raw
    out: dict[str, Any] = {}
    node = out
    parts = key.strip().split(".")
    for part in parts[:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def _scalar(merged: Mapping[str, Any], name: str, kind: Callable[[Any], N]) -> N:
    """Setting ``name`` as a number of ``kind``, or an error naming it and the value."""
    value = merged.get(name)
    try:
        return kind(value)
    except (TypeError, ValueError, OverflowError) as err:
        what = "a whole number" if kind is int else "a number"
        raise ReplayConfigError(
            f"invalid configuration: {name}: expected {what}, got {value!r}"
        ) from err


def _problems(err: ValidationError, part: str) -> str:
    """A pydantic error in one line: each field, what is wrong, the value given (without
    pydantic's own layout and links)."""
    out = []
    for e in err.errors(include_url=False)[:5]:
        loc = part + ".".join(str(p) for p in e["loc"])
        got = repr(e.get("input"))
        out.append(f"{loc}: {e['msg']} (got {got[:60] + '...' if len(got) > 60 else got})")
    return "; ".join(out)


def _unknown(base: Mapping[str, Any], top: Mapping[str, Any], at: str = "") -> list[str]:
    """Dotted keys of ``top`` that ``base`` does not have (the localizer's parameters are
    checked apart, with the list of those it knows)."""
    out = []
    for key, value in top.items():
        name = f"{at}{key}"
        if name == "localizer":
            continue
        if key not in base:
            out.append(name)
        elif isinstance(value, Mapping) and isinstance(base[key], Mapping):
            out += _unknown(base[key], value, f"{name}.")
    return out


def _refuse_unknown(base: Mapping[str, Any], top: Mapping[str, Any], where: str) -> None:
    """Refuse a setting that is no setting of the service's: a misspelt one would otherwise
    change nothing, and the audit would pass under settings the user did not get. (A setting of
    the service's that a replay does not use, such as ``listen`` in the file ``rlutf serve``
    reads, is let through.)"""
    known = {**dict.fromkeys(Settings.model_fields), **base}
    unknown = _unknown(known, top)
    if unknown:
        raise ReplayConfigError(
            f"{where}: no setting of the service is named {', '.join(unknown)} "
            f"(a replay uses: {', '.join(sorted(k for k in base if k != 'localizer'))}, "
            "and localizer.PARAMETER)"
        )


def resolve(
    recorded: Mapping[str, Any] | None,
    *,
    prefix_hint: str | None = None,
    settings_file: Path | None = None,
    assignments: Sequence[str] = (),
) -> ReplayConfig:
    """Merge the recorded configuration, a settings file and ``KEY=VALUE`` assignments.

    Args:
        recorded: the log's ``rlutf.config`` (``None``: defaults).
        prefix_hint: the prefix read from the log's topics, used when nothing sets one.
        settings_file: a settings file merged over the recorded configuration.
        assignments: ``KEY=VALUE`` texts applied last.

    Raises:
        ReplayConfigError: unreadable file, unknown localizer parameter, invalid value.
    """
    merged = _merge(default_settings(prefix_hint), recorded or {})
    if settings_file is not None:
        given = read_settings_file(settings_file)
        _refuse_unknown(merged, given, f"settings file {settings_file}")
        _merge(merged, given)
    for text in assignments:
        given = _assignment(text)
        _refuse_unknown(merged, given, f"--set {text!r}")
        _merge(merged, given)
    loc = merged.get("localizer")
    if not isinstance(loc, dict):
        raise ReplayConfigError("localizer: expected a mapping of localizer parameters")
    known = {f.name for f in fields(LocalizerConfig)}
    unknown = sorted(set(loc) - known)
    if unknown:
        raise ReplayConfigError(
            f"localizer: unknown parameter(s) {', '.join(unknown)} "
            f"(known: {', '.join(sorted(known))})"
        )
    part = "localizer."
    try:
        localizer = TypeAdapter(LocalizerConfig).validate_python(loc)
        part = "limits."
        limits = Limits.model_validate(merged.get("limits") or {})
    except ValidationError as err:
        raise ReplayConfigError(f"invalid configuration: {_problems(err, part)}") from err
    interval = _scalar(merged, "event_interval_s", float)
    max_bytes = _scalar(merged, "max_payload_bytes", int)
    max_map_bytes = _scalar(merged, "max_map_bytes", int)
    map_limits = MapLimits(
        _scalar(merged, "max_map_area", float), _scalar(merged, "max_map_vertices", int)
    )
    prefix = merged.get("prefix")
    if not isinstance(prefix, str) or not prefix:
        raise ReplayConfigError(f"prefix: expected a non-empty string, got {prefix!r}")
    return ReplayConfig(
        prefix,
        localizer,
        int(interval * 1e9),
        max_bytes,
        merged,
        limits,
        max_map_bytes,
        map_limits,
    )
