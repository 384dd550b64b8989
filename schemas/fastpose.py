"""The PoseEstimate payload of one update, written without building the model.

The service writes one PoseEstimate per scan and robot, 2,000 a second at 200 robots, and
building the pydantic model and running :func:`schemas.encode` over it cost ~50 us a pose. For
the common case (no hypotheses, every value in range) :func:`encode_pose` writes the same bytes
from a text template: fields in declaration order, integers and ids as they are, floats by
Python's shortest round-trip ``repr``, exactly as ``json.dumps`` writes them. Anything else goes
through the model, so a value out of range raises what it raised before.
``tests/schemas/test_fastpose.py`` compares the two paths byte for byte.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

from schemas._types import ID_PATTERN, MAX_STAMP_NS
from schemas.codec import encode
from schemas.messages import Hypothesis, PoseEstimate

_ID = re.compile(ID_PATTERN)
#: The head every payload of :func:`encode_pose` starts with: its stamp and robot id.
_HEAD = re.compile(rb'\{"stamp_ns":([0-9]{1,19}),"robot_id":"(' + ID_PATTERN.encode() + rb')",')
_STATUSES = frozenset(("tracking", "corrected", "lost"))
_repr = float.__repr__


def _finite(values: Sequence[float]) -> bool:
    return all(type(v) is float and math.isfinite(v) for v in values)


def _unit(v: float) -> bool:
    return type(v) is float and 0.0 <= v <= 1.0


def _non_negative(v: float) -> bool:
    return type(v) is float and 0.0 <= v < math.inf


def encode_pose(
    stamp_ns: int,
    robot_id: str,
    map_id: str,
    x: float,
    y: float,
    theta: float,
    status: str,
    discrepancy: float,
    iterations: int,
    covariance: Sequence[float] | None = None,
    hypotheses: tuple[Hypothesis, ...] | None = None,
    localization_score: float | None = None,
    deviation_range: float | None = None,
) -> bytes:
    """``encode(PoseEstimate(...))`` of these fields, the same bytes, faster.

    Raises:
        pydantic.ValidationError: a field out of range, as the model raises it.
    """
    cov = () if covariance is None else tuple(covariance)
    if (
        hypotheses is None
        and type(stamp_ns) is int
        and 0 <= stamp_ns <= MAX_STAMP_NS
        and type(iterations) is int
        and iterations >= 0
        and status in _STATUSES
        and type(robot_id) is str
        and type(map_id) is str
        and _ID.fullmatch(robot_id) is not None
        and _ID.fullmatch(map_id) is not None
        and _finite((x, y, theta, discrepancy, *cov))
        and discrepancy >= 0.0
        and (covariance is None or len(cov) == 9)
        and (localization_score is None or _unit(localization_score))
        and (deviation_range is None or _non_negative(deviation_range))
    ):
        text = (
            f'{{"stamp_ns":{stamp_ns},"robot_id":"{robot_id}","map_id":"{map_id}",'
            f'"x":{_repr(x)},"y":{_repr(y)},"theta":{_repr(theta)},"status":"{status}",'
            f'"discrepancy":{_repr(discrepancy)},"iterations":{iterations}'
        )
        if covariance is not None:
            text += ',"covariance":[' + ",".join(map(_repr, cov)) + "]"
        if localization_score is not None:
            text += f',"localization_score":{_repr(localization_score)}'
        if deviation_range is not None:
            text += f',"deviation_range":{_repr(deviation_range)}'
        return (text + "}").encode()
    return encode(
        PoseEstimate(
            stamp_ns=stamp_ns,
            robot_id=robot_id,
            map_id=map_id,
            x=x,
            y=y,
            theta=theta,
            status=status,
            discrepancy=discrepancy,
            iterations=iterations,
            covariance=None if covariance is None else cov,
            hypotheses=hypotheses,
            localization_score=localization_score,
            deviation_range=deviation_range,
        )
    )


def read_head(payload: bytes) -> tuple[int, str] | None:
    """The stamp and robot id at the head of a PoseEstimate written as :func:`encode_pose` (and
    :func:`schemas.encode`) writes it, without decoding the rest; ``None`` for any other text.

    Only the head is read: the rest may still not be a PoseEstimate (decode it to know).
    """
    head = _HEAD.match(payload)
    return None if head is None else (int(head[1]), head[2].decode())
