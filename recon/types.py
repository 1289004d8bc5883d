"""Data passed between reconstruction stages (table frame, millimetres).

Images handed to ``recon`` are already undistorted: one pinhole ``K`` (3, 3)
shared by all views, one ``T_cam_table`` (4, 4) per view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["VoxelHull", "TableMesh", "DepthMap", "FusedPoints"]


@dataclass(frozen=True)
class VoxelHull:
    """A sampled visual hull.

    Attributes
    ----------
    values : (Nx, Ny, Nz) float32
        Signed value at voxel centres, millimetres: > 0 inside the hull, < 0
        outside, the surface at 0 (sub-voxel, from silhouette distance
        transforms); index order (x, y, z) in the table frame.
    origin_table : (3,) float64
        Table coordinates (mm) of the centre of voxel (0, 0, 0).
    voxel_mm : float
        Voxel edge length, mm.
    """

    values: np.ndarray
    origin_table: np.ndarray
    voxel_mm: float
    meta: dict = field(default_factory=dict)

    def centres_table(self, idx: np.ndarray) -> np.ndarray:
        """Table coordinates (N, 3) of integer voxel indices ``idx`` (N, 3)."""
        return self.origin_table + np.asarray(idx, float) * self.voxel_mm


@dataclass(frozen=True)
class TableMesh:
    """A triangle mesh in the table frame (mm), outward normals, vertex colours."""

    vertices_table: np.ndarray  # (N, 3) float64, mm
    faces: np.ndarray  # (M, 3) int64, counter-clockwise seen from outside
    normals_table: np.ndarray | None = None  # (N, 3) float64, unit
    colors_rgb: np.ndarray | None = None  # (N, 3) uint8


@dataclass(frozen=True)
class DepthMap:
    """Per-view depth from multi-view stereo.

    ``depth_mm`` (H, W) float32 is z-depth in the camera frame (0 where
    unknown); ``confidence`` (H, W) float32 in [0, 1].
    """

    view: int
    depth_mm: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class FusedPoints:
    """Fused, coloured point cloud in the table frame (mm)."""

    pts_table: np.ndarray  # (N, 3) float64
    normals_table: np.ndarray  # (N, 3) float64, unit, outward
    colors_rgb: np.ndarray  # (N, 3) uint8
