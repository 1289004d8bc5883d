"""Writing point clouds (PLY with normals and colours), atomically."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

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
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".ply")
    os.close(fd)
    try:
        if not o3d.io.write_point_cloud(tmp, pc, write_ascii=False):
            raise OSError(f"{path}: open3d could not write the point cloud")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
