"""Writing point clouds (PLY with normals and colours), atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.fileio import atomic_path
from recon.types import FusedPoints

__all__ = ["write_points_ply"]


def write_points_ply(path: str | Path, points: FusedPoints, *, metres: bool = False) -> Path:
    """Binary PLY of the fused points (table frame; mm unless ``metres``)."""
    import open3d as o3d

    path = Path(path)
    s = 1e-3 if metres else 1.0
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points.pts_table, float) * s))
    pc.normals = o3d.utility.Vector3dVector(np.asarray(points.normals_table, float))
    pc.colors = o3d.utility.Vector3dVector(np.asarray(points.colors_rgb, float) / 255.0)
    with atomic_path(path, suffix=".ply") as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False):
            raise OSError(f"{path}: open3d could not write the point cloud")
    return path
