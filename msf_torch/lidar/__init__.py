"""2D LiDAR front end: point-to-line ICP between scans, scan odometry as a pose source, and
occupancy-grid maps."""

from msf_torch.lidar.grid import GridConfig, OccupancyGrid, occupancy_grid, read_map, write_map
from msf_torch.lidar.odometry import ScanOdometry, pose_source, scan_odometry
from msf_torch.lidar.plicp import PlicpConfig, PlicpResult, plicp, scan_points

__all__ = [
    "GridConfig",
    "OccupancyGrid",
    "PlicpConfig",
    "PlicpResult",
    "ScanOdometry",
    "occupancy_grid",
    "plicp",
    "pose_source",
    "read_map",
    "scan_odometry",
    "scan_points",
    "write_map",
]
