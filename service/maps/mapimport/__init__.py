"""Map import and build: ROS map_server grids and laser logs to wire Maps, and map rendering.

The functions behind ``rlutf map import|build|show``::

    from service.maps.mapimport import import_grid, build_from_carmen, grid_to_map, render_map

    result = import_grid("maps/depot.yaml")              # ImportResult(map, report, ...)
    print("\\n".join(result.report))
    render_map(result.map, "depot.png")

    grid = build_from_carmen("intel-corrected.log.gz")   # OccupancyGrid
    result = grid_to_map(grid, map_id="intel")

Every deliberate error is a :class:`MapImportError` whose message names the file, key or value.
"""

from service.maps.mapimport.build import (
    DEFAULT_MAX_RANGE,
    MAX_GRID_CELLS,
    CarmenLog,
    CarmenScan,
    build_from_carmen,
    build_grid,
    carmen_angles,
    max_grid_cells,
    parse_carmen,
    read_carmen,
)
from service.maps.mapimport.errors import (
    CarmenError,
    ComponentError,
    EmptyMapError,
    GridTooLargeError,
    MapFileError,
    MapImportError,
    MapYamlError,
)
from service.maps.mapimport.grid import (
    MapMetadata,
    OccupancyGrid,
    encode_map_yaml,
    encode_pgm,
    grid_from_image,
    load_grid,
    parse_map_yaml,
    save_grid,
)
from service.maps.mapimport.importer import (
    BUILT_SURFACE_CELLS,
    ImportResult,
    grid_to_map,
    import_grid,
    map_id_from_name,
    parse_component,
)
from service.maps.mapimport.polygonize import (
    DEFAULT_MIN_AREA,
    DEFAULT_MIN_HOLE_AREA,
    Component,
    ComponentSpec,
    Polygonized,
    polygonize,
    trace_free_space,
)
from service.maps.mapimport.raymarch import march_rays, traverse
from service.maps.mapimport.render import render_map

__all__ = [
    "BUILT_SURFACE_CELLS",
    "DEFAULT_MAX_RANGE",
    "DEFAULT_MIN_AREA",
    "DEFAULT_MIN_HOLE_AREA",
    "MAX_GRID_CELLS",
    "CarmenError",
    "CarmenLog",
    "CarmenScan",
    "Component",
    "ComponentError",
    "ComponentSpec",
    "EmptyMapError",
    "GridTooLargeError",
    "ImportResult",
    "MapFileError",
    "MapImportError",
    "MapMetadata",
    "MapYamlError",
    "OccupancyGrid",
    "Polygonized",
    "build_from_carmen",
    "build_grid",
    "carmen_angles",
    "encode_map_yaml",
    "encode_pgm",
    "grid_from_image",
    "grid_to_map",
    "import_grid",
    "load_grid",
    "map_id_from_name",
    "march_rays",
    "max_grid_cells",
    "parse_carmen",
    "parse_component",
    "parse_map_yaml",
    "polygonize",
    "read_carmen",
    "render_map",
    "save_grid",
    "trace_free_space",
    "traverse",
]
