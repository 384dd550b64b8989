"""Compile the localizer's kernels before the first scan needs them.

numba compiles a kernel on its first call, about 15 s for all of them on a small machine, and
keeps the machine code in its cache (beside the sources, or in ``NUMBA_CACHE_DIR``), from where
a later process loads it in well under a second. A service calls :func:`warm_up` once per
process at start, so that no robot's first scan waits for the compiler.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
from shapely.geometry import box

from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.map import Map
from rlutf.mapchange import ChangeGrid
from rlutf.raycast import cast_rays
from rlutf.scan import Scan


def _numba_without_blas() -> None:
    """Load numba's array functions without scipy's BLAS, which no kernel here uses.

    numba's ``numba.np.arraymath`` imports ``scipy.linalg.cython_blas``, when scipy is
    installed (scikit-image requires it), only to tell whether ``np.dot`` can be compiled; that
    import brings in ``scipy.linalg`` and its libraries, 12 MB of resident memory in every
    process that loads the kernels. Hidden while the module loads, the check finds no BLAS:
    ``np.dot`` and ``np.linalg`` would not compile in a kernel (none calls them), and scipy
    stays importable for any other use. Nothing is done when the module is already loaded.
    """
    blas = "scipy.linalg.cython_blas"
    if "numba.np.arraymath" in sys.modules or blas in sys.modules:
        return
    sys.modules[blas] = None  # type: ignore[assignment]  # import raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules[blas]


def kernels() -> list[Any]:
    """The localizer's compiled kernels: every numba dispatcher of its kernel modules."""
    from rlutf import _bnb, _changes, _grid, _kernels, _lm

    modules = (_bnb, _changes, _grid, _kernels, _lm)
    return [v for m in modules for v in vars(m).values() if getattr(v, "stats", None) is not None]


def compiled_here() -> bool:
    """Whether this process compiled any of the localizer's kernels (numba's cache did not hold
    them: a first start after an install, or a cache that does not match the sources).

    Such a process keeps the compiler's memory for as long as it runs: about 290 MB resident
    after :func:`warm_up` against about 160 MB for one that loaded the kernels from the cache
    (CPython 3.11, numba 0.68). From numba's per-kernel cache statistics."""
    return any(getattr(kernel.stats, "cache_misses", None) for kernel in kernels())


def warm_up() -> bool:
    """Run every kernel once, with the argument types the localizer passes, on a small map.

    Returns:
        :func:`compiled_here`: whether this process compiled kernels (rather than loading all of
        them from numba's cache).
    """
    _numba_without_blas()
    world = Map.from_shapely(box(0.0, 0.0, 6.0, 4.0).difference(box(2.5, 1.5, 3.0, 2.5)))
    pose = np.array([1.2, 1.0, 0.3])
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    ranges = cast_rays(world, pose, angles, 8.0)[0]
    scan = Scan.create(ranges, -math.pi, 2.0 * math.pi / 90, 0.05, 8.0)
    slip = np.array([0.05, -0.03, 0.02])
    for config in (
        LocalizerConfig(),
        LocalizerConfig(refine=False),
        LocalizerConfig(discrepancy="turning"),
    ):
        # The first update searches wide (field and refinement); the second starts off the
        # pose, so the random search scores candidates.
        loc = Localizer(world, pose, config, spread=(0.1, 0.05))
        loc.update(np.zeros(3), scan)
        result = loc.update(slip, scan)
        if result.returns is not None:
            # Map health's evidence of a scan (the service counts every update's returns):
            # not compiled here, each worker compiled it at its first scan, a second and more
            # in which its robots' scans waited and were dropped.
            ChangeGrid(world).add(result.returns, 1_000_000_000, "warm-up")
    # A relocalization: the map's search grid and the branch and bound.
    loc = Localizer(world, pose)
    loc.relocalize()
    loc.update(np.zeros(3), scan)
    return compiled_here()
