"""Exact ray casting against a polygon map.

Each ray walks the cells of the map's wall grid that it crosses, nearest first, and tests only
the walls listed in them; it stops at the first cell whose nearest hit lies inside it. The cost
of a ray therefore grows with the cells it crosses and the walls in them, not with the size of
the map, and every (ray, wall) pair tested is solved exactly, so the result equals brute-force
segment intersection. The loop is compiled (:mod:`rlutf._kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.map import Map

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Beams:
    """Beam directions, prepared once per scan geometry.

    Attributes:
        angles: ``(N,)`` beam angles, radians, relative to the ray origin's heading.
        cos: ``(N,)`` cosines of ``angles``.
        sin: ``(N,)`` sines of ``angles``.
    """

    angles: FloatArray
    cos: FloatArray
    sin: FloatArray

    @classmethod
    def of(cls, angles: ArrayLike) -> Beams:
        """Prepare beams from ``(N,)`` angles in radians."""
        a = np.array(angles, dtype=np.float64).reshape(-1)
        cos, sin = np.cos(a), np.sin(a)
        return cls(a, cos, sin)

    def __len__(self) -> int:
        return len(self.angles)

    def take(self, index: NDArray[np.int64]) -> Beams:
        """The beams at ``index``, in that order."""
        if len(index) == len(self.angles):
            return self
        return Beams(self.angles[index], self.cos[index], self.sin[index])

    def select(self, mask: NDArray[np.bool_]) -> Beams:
        """The beams where ``(N,)`` ``mask`` is true, in their order."""
        keep = np.asarray(mask, dtype=bool)
        if keep.all():
            return self
        return Beams(self.angles[keep], self.cos[keep], self.sin[keep])


def cast_rays(
    world: Map, poses: ArrayLike, angles: ArrayLike | Beams, max_range: float
) -> FloatArray:
    """Ranges from each pose along each beam to the nearest wall.

    Args:
        world: the map.
        poses: ``(K, 3)`` ray origins and headings ``(x, y, theta)`` in the map frame (or one
            ``(3,)`` pose).
        angles: ``(N,)`` beam angles in radians relative to each pose's heading, or
            :class:`Beams` prepared from them.
        max_range: hits farther than this (metres) count as no hit.

    Returns:
        ``(K, N)`` ranges in metres; ``inf`` where a beam hits no wall within ``max_range``.
    """
    return cast_with_walls(world, poses, angles, max_range)[0]


def cast_with_walls(
    world: Map, poses: ArrayLike, angles: ArrayLike | Beams, max_range: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`cast_rays` and the index of the wall each beam hits (``-1`` for none)."""
    from rlutf import _kernels

    beams = angles if isinstance(angles, Beams) else Beams.of(angles)
    p = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 3))
    if not max_range > 0 or len(beams) == 0 or len(p) == 0:
        return np.full((len(p), len(beams)), np.inf), np.full((len(p), len(beams)), -1)
    ranges, walls = _kernels.cast_poses(
        p, beams.cos, beams.sin, float(max_range), False, *world.grid
    )
    return ranges, walls
