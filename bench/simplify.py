"""Simplifying a map with thousands of obstacles: the whole geometry against ring by ring.

Run: ``python -m bench.simplify [--size 800] [--write]``.

Two steps simplify a map's walls with the topology preserved: ``rlutf map import`` and ``rlutf
map build`` (half a cell, :func:`service.maps.mapimport.polygonize`), and the service when it
prepares a map for tracking (the walls simplified at ``localizer.coarse_tolerance``, 7 cm,
:func:`rlutf.map.coarse_map`). GEOS's simplifier on the whole geometry costs time growing with
the square of its holes; :func:`rlutf.simplify.simplify_rings` simplifies apart the groups of
rings that cannot meet in its checks and gives the same vertices. For each map, both ways at
both tolerances (CPU seconds of this process, one run each) and whether the results are the
same vertex for vertex; then ``rlutf map import``'s import of the cluttered grid (its YAML and
PGM written to a temporary folder), end to end, with each simplifier.

Maps: a site of ``--size`` x ``--size`` cells at 5 cm with obstacles of 2 x 2 cells scattered at
random, one per :data:`CELLS_PER_OBSTACLE` cells (racks' legs, posts and clutter in a grid); the
10 MB warehouse of :mod:`bench.bigmap` (5,200 racks); the intel and aces maps built from their
logs' even scans (:func:`bench.evenodd_runs.even_map`).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from bench.report import section_main

SECTION = "simplify"
#: Resolution of the generated site, metres.
CELL = 0.05
#: Cells of the site per obstacle (each 2 x 2 cells: 10 cm, a rack's leg or a post, which an
#: import keeps; single cells are filled as noise).
CELLS_PER_OBSTACLE = 30
#: The tolerances: ``rlutf map import``'s (half a cell) and the coarse walls' (7 cm).
TOLERANCES = (0.025, 0.07)


def site_grid(size: int, seed: int = 1) -> np.ndarray:
    """``(size, size)`` free cells of the cluttered site, row 0 at the top: walls round it,
    obstacles at random inside (some overlapping, some against the walls)."""
    free = np.zeros((size, size), dtype=bool)
    free[1:-1, 1:-1] = True
    corner = np.random.default_rng(seed).integers(
        1, size - 3, size=(size**2 // CELLS_PER_OBSTACLE, 2)
    )
    for dr in (0, 1):
        for dc in (0, 1):
            free[corner[:, 0] + dr, corner[:, 1] + dc] = False
    return free


def write_site(free: np.ndarray, folder: Path) -> Path:
    """The grid as a map_server YAML and PGM in ``folder``; returns the YAML's path."""
    image = np.where(free, 254, 0).astype(np.uint8)
    rows, cols = image.shape
    (folder / "site.pgm").write_bytes(f"P5\n{cols} {rows}\n255\n".encode() + image.tobytes())
    (folder / "site.yaml").write_text(
        f"image: site.pgm\nresolution: {CELL}\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    return folder / "site.yaml"


def _cpu(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[float, Any]:
    start = time.process_time()
    out = fn(*args, **kwargs)
    return time.process_time() - start, out


def _same(a: shapely.Geometry, b: shapely.Geometry) -> bool:
    return (
        a.geom_type == b.geom_type
        and np.array_equal(shapely.get_coordinates(a), shapely.get_coordinates(b))
        and bool(shapely.equals_exact(a, b, 0.0))
    )


def maps(size: int) -> list[tuple[str, shapely.Geometry]]:
    """The maps measured, by name."""
    from bench.bigmap import warehouse_payload
    from bench.evenodd_runs import even_map
    from service.live.worker import world_of_payload
    from service.maps.mapimport.polygonize import trace_free_space

    site = trace_free_space(site_grid(size), CELL)
    return [
        (f"cluttered site, {size} x {size} cells", site),
        ("warehouse, 10 MB", world_of_payload(warehouse_payload(10.0)[0]).geometry),
        ("intel, built from its even scans", even_map("intel").geometry),
        ("aces, built from its even scans", even_map("aces").geometry),
    ]


def simplify_rows(named: list[tuple[str, shapely.Geometry]]) -> list[str]:
    """A table row per map and tolerance."""
    from rlutf.simplify import simplify_rings

    rows = []
    for name, geom in named:
        holes = sum(len(p.interiors) for p in shapely.get_parts(geom))
        walls = len(shapely.get_coordinates(geom)) - len(shapely.get_parts(geom)) - holes
        for tol in TOLERANCES:
            whole_s, whole = _cpu(shapely.simplify, geom, tol, preserve_topology=True)
            rings_s, rings = _cpu(simplify_rings, geom, tol)
            rows.append(
                f"| {name} | {holes:,} | {walls:,} | {100 * tol:g} | {whole_s:.2f} | "
                f"{rings_s:.2f} | {whole_s / max(rings_s, 1e-9):.1f} | "
                f"{'yes' if _same(whole, rings) else 'NO'} |"
            )
    return rows


def import_rows(size: int) -> list[str]:
    """``import_grid`` of the cluttered site, end to end, with each simplifier."""
    from service.maps.mapimport import import_grid

    # the module (the package's name of that name is its function)
    polygonize: Any = importlib.import_module("service.maps.mapimport.polygonize")
    folder = Path(tempfile.mkdtemp(prefix="rlutf-bench-simplify-"))
    rows = []
    try:
        yaml = write_site(site_grid(size), folder)
        mine = polygonize.simplify_rings

        def whole(g: shapely.Geometry, t: float) -> shapely.Geometry:
            return shapely.simplify(g, t, preserve_topology=True)

        results = {}
        for label, fn in (("whole geometry", whole), ("ring by ring", mine)):
            polygonize.simplify_rings = fn
            try:
                seconds, result = _cpu(import_grid, yaml, map_id="site")
            finally:
                polygonize.simplify_rings = mine
            results[label] = json.dumps(result.map)
            rows.append(f"| {label} | {seconds:.2f} | {result.polygons.wall_count:,} |")
        same = len(set(results.values())) == 1
        rows.append(f"| the two Map JSON documents the same | {'yes' if same else 'NO'} | |")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return rows


def render(args: argparse.Namespace) -> str:
    """Measure and return the section."""
    started = time.time()
    table = simplify_rows(maps(args.size))
    imported = import_rows(args.size)
    return "\n".join(
        [
            f"Command: `python -m bench.simplify --size {args.size} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}, shapely {shapely.__version__} (GEOS "
            f"{shapely.geos_version_string}); CPU seconds of one process, one run each; "
            f"{time.time() - started:.0f} s in all. Load average at the end: "
            f"{os.getloadavg()[0]:.1f}.",
            "",
            "| map | holes | walls | tolerance cm | whole geometry s | ring by ring s | "
            "ratio | same vertices |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
            *table,
            "",
            f"`rlutf map import` of the cluttered site ({args.size} x {args.size} cells, "
            "`service.maps.mapimport.import_grid`), end to end:",
            "",
            "| simplifier | CPU s | walls |",
            "| --- | ---: | ---: |",
            *imported,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.simplify",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--size", type=int, default=800, help="cells a side of the cluttered site")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
