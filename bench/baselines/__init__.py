"""What users would run instead of RLuTF: point-to-line ICP and an AMCL-style particle filter.

Both track one robot from a known start pose with the same inputs as
:class:`rlutf.Localizer`: the odometry motion since the previous scan, in the robot frame, and
the scan. Each returns an :class:`Estimate` per scan.
"""

from bench.baselines.amcl import AmclConfig, ParticleFilter
from bench.baselines.common import Estimate, scan_points
from bench.baselines.icp import IcpConfig, PointToLineIcp

__all__ = [
    "AmclConfig",
    "Estimate",
    "IcpConfig",
    "ParticleFilter",
    "PointToLineIcp",
    "scan_points",
]
