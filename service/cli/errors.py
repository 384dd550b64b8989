"""What a command says when it cannot do its job: a few lines naming the file or flag, the
problem and the fix, never a traceback (``--debug`` shows one).

Commands raise :class:`CliError` for what they foresee; :func:`explain` turns the errors every
command may meet (a path that is missing or not writable, a port in use, zenoh) into the same
kind of message, so the entry point can answer any of them without a traceback.
"""

from __future__ import annotations

import errno
import json
import os
import re
from collections.abc import Sequence

EXIT_OK = 0
#: The task failed: nothing answered, the service refused, the time ran out.
EXIT_FAILURE = 1
#: Bad input: a flag, a settings file, a path or a file's content.
EXIT_USAGE = 2

#: What to try when no zenoh router answers on the endpoints given.
UNREACHABLE_HINT = (
    "is `rlutf serve` running? use -e/--connect ENDPOINT to reach it (default tcp/127.0.0.1:7447)"
)

#: A Rust source location zenoh appends to its messages (`` at /root/.cargo/.../x.rs:12.``).
_RUST_PLACE = re.compile(r"\s*\bat\s+\S+\.rs:\d+(:\d+)?\.?")


class CliError(Exception):
    """A command cannot go on.

    Args:
        message: the problem and the fix, naming the file or flag (one to a few lines).
        code: the exit code (:data:`EXIT_FAILURE` by default; :data:`EXIT_USAGE` for bad input).
    """

    def __init__(self, message: str, code: int = EXIT_FAILURE) -> None:
        super().__init__(message)
        self.code = code


def zenoh_text(err: BaseException) -> str:
    """A zenoh error's message without the Rust source path it carries."""
    text = _RUST_PLACE.sub("", str(err)).strip()
    return text.rstrip(".!") or type(err).__name__


def session_failure(err: BaseException, listen: Sequence[str]) -> str:
    """Why a service's Zenoh session did not open, and what to do: a port another program
    holds, or an endpoint that is not one (``tcp/127.0.0.1:99999``)."""
    text = zenoh_text(err)
    if "in use" in text.lower():
        where = f" on {', '.join(listen)}" if listen else ""
        return (
            f"cannot open the zenoh session ({text}); the port is taken (another `rlutf serve` "
            f"or zenohd{where}?): choose another with -l/--listen, or join it with -m client "
            "-e ENDPOINT"
        )
    return (
        f"cannot open the zenoh session ({text}); check the endpoints (-l/--listen, "
        "-e/--connect, -c/--config): PROTOCOL/HOST:PORT, e.g. tcp/0.0.0.0:7447"
    )


def _os_message(err: OSError) -> tuple[str, int]:
    name = err.filename
    what = err.strerror or str(err)
    if err.errno == errno.EADDRINUSE:
        return (
            f"address already in use ({what}): another program holds the port (a second "
            "`rlutf serve`?); stop it or choose another port",
            EXIT_FAILURE,
        )
    if name is None:
        return f"{what}", EXIT_FAILURE
    if isinstance(err, FileNotFoundError):
        return f"{name}: no such file or directory; check the path (or create the folder)", (
            EXIT_USAGE
        )
    if isinstance(err, PermissionError):
        return f"{name}: permission denied; choose a path you may read or write", EXIT_USAGE
    if isinstance(err, IsADirectoryError):
        return f"{name}: is a folder; give a file name", EXIT_USAGE
    if isinstance(err, NotADirectoryError):
        return f"{name}: a part of the path is a file, not a folder; check the path", EXIT_USAGE
    return f"{name}: {what}", EXIT_FAILURE


def explain(err: BaseException) -> tuple[str, int] | None:
    """``err`` as a message and an exit code, or ``None`` for an error no command foresees."""
    from service.logs.mcapfile import SchemaMissing

    if isinstance(err, CliError):
        return str(err), err.code
    if isinstance(err, SchemaMissing):  # a log would be written that no audit can read
        return str(err), EXIT_FAILURE
    if isinstance(err, OSError):
        return _os_message(err)
    if isinstance(err, json.JSONDecodeError):
        return (
            f"not valid JSON at line {err.lineno}, column {err.colno}: {err.msg}",
            EXIT_USAGE,
        )
    if isinstance(err, UnicodeDecodeError):
        return "the file is not UTF-8 text (a binary or foreign file?)", EXIT_USAGE
    if type(err).__name__ == "SettingsError" and type(err).__module__.startswith("pydantic_"):
        return _environment_message(err), EXIT_USAGE
    if type(err).__module__.startswith("zenoh"):
        text = zenoh_text(err)
        if "Address already in use" in text:
            hint = "the port is taken (another `rlutf serve`, demo or zenohd?); choose another"
        elif "Unable to connect" in text:
            hint = UNREACHABLE_HINT
        else:
            hint = "check the zenoh flags (-m, -l, -e, -c)"
        return f"zenoh: {text}; {hint}", EXIT_FAILURE
    return None


def _environment_message(err: BaseException) -> str:
    """pydantic-settings' error for an ``RLUTF_*`` variable of a nested setting (``localizer``,
    ``ros2``, ``limits``) or a list that is not JSON: the variable, its problem and the fix.

    Before, ``RLUTF_LOCALIZER=garbage`` (or ``RLUTF_ROS2__ROBOTS=r7``) made every command exit 1
    with "unexpected error: SettingsError: error parsing value for field ...", naming no
    variable.
    """
    found = re.search(r'field "(\w+)"', str(err))
    field = found.group(1) if found else ""
    prefix = f"RLUTF_{field.upper()}"
    names = []
    for name, value in sorted(os.environ.items()):
        if name.upper() == prefix or name.upper().startswith(prefix + "__"):
            try:
                json.loads(value)
            except ValueError:
                names.append(name)
    cause = err.__cause__
    why = f" ({str(cause).split(':')[0]})" if isinstance(cause, ValueError) else ""
    given = " or ".join(names[:3]) or f"{prefix} or {prefix}__*"
    return (
        f"invalid configuration: {given} in the environment is not valid JSON{why}: a nested "
        f"setting is given as a JSON object ({prefix}='{{\"name\": value}}') or one variable "
        f"per name ({prefix}__NAME=value); `rlutf config` prints the settings"
    )


def unanswered_hint(args: object) -> str:
    """What to check when no instance answered a query: the service, the endpoint and prefix,
    and with a zenoh file (``-c``, a deployment's TLS identity), the router's access control,
    which drops a query this identity may not make without a word (a robot's certificate)."""
    hint = "is `rlutf serve` running? use -e/--connect and --prefix"
    if getattr(args, "config", None) is not None:
        hint += "; with access control, may the identity of the -c file query it?"
    return hint
