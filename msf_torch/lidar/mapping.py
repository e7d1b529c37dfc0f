"""Scans in, map out: scan odometry (PLICP), an occupancy grid over its poses, files.

:func:`map_from_scans` is what ``msf lidar-map`` runs. It writes into ``out_dir``:

* ``map.png`` + ``map.yaml``: the occupancy grid in ROS ``map_server`` form
  (:func:`msf_torch.lidar.grid.write_map`);
* ``lidar_odometry.tum``: the chained scan poses (z = 0, yaw quaternions);
* ``lidar_graph.g2o``: the same chain as a 2-D pose graph (``VERTEX_SE2`` per scan,
  ``EDGE_SE2`` per matched pair with the inverse of PLICP's covariance as information), for
  loop closures added elsewhere and ``msf posegraph`` (:mod:`msf_torch.io.g2o_2d`);

and returns a summary (scan count, PLICP iterations, degenerate and failed pairs, the map's
size, and with a ``truth`` key in the scans the final and rms position error of the chain
and of the wheel odometry).
"""

from __future__ import annotations

__all__ = ["map_from_scans", "scan_pose_graph"]

import os
from pathlib import Path
from typing import Any

import torch

from msf_torch.io.g2o_2d import PoseGraph2D, write_g2o_2d
from msf_torch.io.tum import write_tum
from msf_torch.lidar.grid import GridConfig, occupancy_grid, write_map
from msf_torch.lidar.odometry import ScanOdometry, pose_source, scan_odometry
from msf_torch.lidar.plicp import PlicpConfig
from msf_torch.types import Trajectory


def _errors(poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    distance = (poses[:, :2] - truth[:, :2]).norm(dim=-1)
    return {"final_m": float(distance[-1]), "rms_m": float(distance.pow(2).mean().sqrt())}


def scan_pose_graph(chain: ScanOdometry) -> PoseGraph2D:
    """The scan odometry as a planar pose graph: vertex k the chained pose of scan k, edge
    k -> k + 1 the matched relative pose with information = covariance^-1 (symmetrised).

    Args:
        chain: :class:`~msf_torch.lidar.odometry.ScanOdometry` of N scans.

    Returns:
        a float64 :class:`~msf_torch.io.g2o_2d.PoseGraph2D` (N vertices, N - 1 edges).
    """
    count = chain.pose.shape[0]
    information = torch.linalg.inv(chain.relative_covariance.to(torch.float64))
    index = torch.arange(count - 1)
    return PoseGraph2D(
        vertex_ids=torch.arange(count),
        positions=chain.pose[:, 0:2].to(torch.float64).contiguous(),
        headings=chain.pose[:, 2].to(torch.float64).contiguous(),
        edge_index=torch.stack((index, index + 1), -1),
        edge_translations=chain.relative[:, 0:2].to(torch.float64).contiguous(),
        edge_headings=chain.relative[:, 2].to(torch.float64).contiguous(),
        edge_information=0.5 * (information + information.mT),
    )


def map_from_scans(
    scans: dict[str, torch.Tensor],
    out_dir: str | os.PathLike[str],
    grid_config: GridConfig | None = None,
    plicp_config: PlicpConfig | None = None,
    use_odometry: bool = True,
) -> dict[str, Any]:
    """Scan odometry and an occupancy map from scans (see the module docstring).

    Args:
        scans: ``t`` (N,), ``angles`` (K,), ``ranges`` (N, K) and optionally ``odometry``
            and ``truth`` (N, 3), as :func:`msf_torch.io.scans.read_scans` returns them.
        out_dir: output folder (created).
        grid_config: occupancy-grid settings.
        plicp_config: PLICP settings.
        use_odometry: initial guesses from ``scans["odometry"]`` when present (else
            identity).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    odometry = scans.get("odometry") if use_odometry else None
    start = scans["truth"][0] if "truth" in scans else None
    if start is None and odometry is not None:
        start = odometry[0]
    chain = scan_odometry(
        scans["t"], scans["ranges"], scans["angles"], odometry, plicp_config, start=start
    )
    grid = occupancy_grid(chain.pose, scans["ranges"], scans["angles"], grid_config)
    png, yaml_path = write_map(grid, out / "map")
    source = pose_source(chain)
    trajectory = Trajectory(
        t=source.t, position=source.position, quaternion=source.quaternion, mask=source.mask
    )
    tum = write_tum(trajectory, out / "lidar_odometry.tum")
    graph = write_g2o_2d(out / "lidar_graph.g2o", scan_pose_graph(chain))
    summary: dict[str, Any] = {
        "scans": int(scans["t"].shape[0]),
        "initial_guess": "odometry" if odometry is not None else "identity",
        "iterations_mean": float(chain.iterations.double().mean()),
        "converged_pairs": int(chain.converged.sum()),
        "degenerate_pairs": int(chain.degenerate.sum()),
        "failed_pairs": int(chain.failed.sum()),
        "map_cells": list(grid.log_odds.shape),
        "occupied_cells": int((grid.trinary() == 1).sum()),
        "free_cells": int((grid.trinary() == 0).sum()),
        "files": {
            "png": str(png),
            "yaml": str(yaml_path),
            "trajectory": str(tum),
            "graph": str(graph),
        },
    }
    if "truth" in scans:
        summary["lidar_error"] = _errors(chain.pose, scans["truth"])
        if "odometry" in scans:
            summary["wheel_error"] = _errors(scans["odometry"], scans["truth"])
    return summary
