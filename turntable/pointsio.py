"""Writing point clouds (PLY with normals and colours), atomically."""

from __future__ import annotations

import errno
import shutil
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
        # open3d may report success for a file cut short by a full disk: count what landed
        if (not o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False)
                or len(o3d.io.read_point_cloud(str(tmp), format="ply").points) != len(pc.points)):
            # it says only "failed": free space tells the likely reason
            raise OSError(errno.ENOSPC if _disk_full(tmp, len(pc.points)) else errno.EIO,
                          "open3d could not write the point cloud", str(path))
    return path


def _disk_full(path: Path, n_points: int) -> bool:
    """Whether the disk holding ``path`` has less room left than the points need (51 bytes each)."""
    try:
        return shutil.disk_usage(path.parent).free < 51 * n_points + (1 << 16)
    except OSError:
        return False
