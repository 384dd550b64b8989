"""What ``rlutf simulate`` tells of its fleet as it drives it: the robots' own Events, counted
by code, and the progress and summary lines of poses, errors and latency."""

from __future__ import annotations

import contextlib
import json
import math
from collections import Counter
from typing import Any


def robot_of(keys: Any, ids: frozenset[str], sample: Any) -> str | None:
    """The robot of a sample's key (``{prefix}/robots/{robot}/...``) if it is one of ``ids``."""
    with contextlib.suppress(ValueError):
        parsed = keys.parse_robot_key(str(sample.key_expr))
        if parsed is not None and parsed[0] in ids:
            return str(parsed[0])
    return None


def event_counter(keys: Any, ids: tuple[str, ...], events: Counter[str]) -> Any:
    """What counts, in ``events`` by code, the Events of the robots ``ids`` heard on
    ``{prefix}/robots/*/events``: other robots' Events on the bus (another fleet, a broken
    client) are not this fleet's, and cost a key test (one subscriber, not one per robot)."""
    ours = frozenset(ids)

    def on_event(sample: Any) -> None:
        if robot_of(keys, ours, sample) is None:
            return
        with contextlib.suppress(ValueError, AttributeError):
            events[str(json.loads(sample.payload.to_bytes()).get("code"))] += 1

    return on_event


def progress(elapsed: float, board: Any, events: Counter[str], rejected: int) -> str:
    import numpy as np

    scores = board.snapshot()
    sent = sum(s.sent for s in scores)
    poses = sum(s.poses for s in scores)
    placed = sum(1 for s in scores if s.poses)
    recent = [s.errors[-1] for s in scores if s.errors]
    line = f"[{elapsed:6.1f} s] sent {sent} scans, got {poses} poses; {placed} of {len(scores)} "
    line += "robots localized"
    if recent:
        line += (
            f"; last error median {100 * float(np.median(recent)):.1f} cm, "
            f"max {100 * max(recent):.1f} cm"
        )
    latencies = [s.latency_ms(50) for s in scores if s.latencies_ms]
    if latencies:
        line += f"; latency p50 {float(np.median(latencies)):.1f} ms"
    if events:
        line += "; events " + ", ".join(f"{code} {n}" for code, n in sorted(events.items()))
    if rejected:
        line += f"; bad inputs sent {rejected}"
    return line


def summary(board: Any) -> list[str]:
    import numpy as np

    rows = [f"{'robot':<10} {'poses/scans':>12} {'RMSE cm':>8} {'max cm':>7}  statuses"]
    for s in board.snapshot():
        if not s.errors:
            rows.append(f"{s.robot_id:<10} {f'0/{s.sent}':>12} {'-':>8} {'-':>7}  -")
            continue
        e = np.asarray(s.errors)
        statuses = ", ".join(f"{k} {n}" for k, n in sorted(s.statuses.items()))
        rows.append(
            f"{s.robot_id:<10} {f'{s.poses}/{s.sent}':>12} "
            f"{100 * math.sqrt(float(np.mean(e**2))):>8.1f} {100 * float(e.max()):>7.1f}  "
            f"{statuses}"
        )
    return rows
