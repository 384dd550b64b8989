"""RLuTF: Robot Localization using Turning Function.

The pure algorithm library: arrays in, arrays out; no files, sockets, clocks, threads or logging.
"""

from rlutf.discrepancy import anchored_turning, polar_area, turning_steps
from rlutf.errors import ConfigError, GeometryError, MapError, RlutfError
from rlutf.localizer import Localizer, LocalizerConfig, LocalizeResult
from rlutf.map import Map
from rlutf.motion import compose, interpolate, inverse, relative, wrap_angle
from rlutf.raycast import Beams, cast_rays
from rlutf.refine import Refinement, RefineSettings, refine_pose
from rlutf.relocalize import Hypothesis, Relocalization, RelocalizeSettings, relocalize
from rlutf.scan import Scan
from rlutf.turning import TurningMatch, turning_distance, turning_function, turning_match
from rlutf.warmup import warm_up

__all__ = [
    "Beams",
    "ConfigError",
    "GeometryError",
    "Hypothesis",
    "LocalizeResult",
    "Localizer",
    "LocalizerConfig",
    "Map",
    "MapError",
    "RefineSettings",
    "Refinement",
    "Relocalization",
    "RelocalizeSettings",
    "RlutfError",
    "Scan",
    "TurningMatch",
    "anchored_turning",
    "cast_rays",
    "compose",
    "interpolate",
    "inverse",
    "polar_area",
    "refine_pose",
    "relative",
    "relocalize",
    "turning_distance",
    "turning_function",
    "turning_match",
    "turning_steps",
    "warm_up",
    "wrap_angle",
]
