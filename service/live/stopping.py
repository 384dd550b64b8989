"""A child process that ends while its service is being stopped ends with it.

A service stopped as a whole has every process signalled at once: a terminal's Ctrl-C sends
SIGINT to the foreground process group, and ``systemctl stop`` (``KillMode=control-group``, the
default), ``timeout`` and ``kill -- -PGID`` send SIGTERM to the worker processes and to a host's
service processes as well as to the service. A child may then end a moment before the service's
own signal handler has run. Such a child is not lost: it is neither reported (no
``worker_lost``, no error) nor started again (a replacement started while the service stops held
the stop up by 10 to 20 s).
"""

from __future__ import annotations

import signal
import threading
from typing import Final

#: Signals that stop a whole service (its children's exit codes are their negatives).
STOP_SIGNALS: Final = frozenset((signal.SIGTERM, signal.SIGINT, signal.SIGHUP))
#: Seconds a child that a stop signal ended (or that stopped cleanly, exit code 0) waits for
#: the service's own stop before it is taken for lost: the same signal reaches the service at
#: the same moment, and its main thread runs the handler within a second
#: (``LocalizationService.wait``'s timed waits).
STOP_GRACE_S: Final = 2.0


def ended_with_the_service(code: int | None, stop: threading.Event) -> bool:
    """Whether a child that exited with ``code`` ended because its service is being stopped:
    it stopped cleanly (0) or by a stop signal, and ``stop`` (set by the service's signal
    handler) is set within :data:`STOP_GRACE_S`."""
    if code is None or (code != 0 and -code not in STOP_SIGNALS):
        return False
    return stop.wait(STOP_GRACE_S)
