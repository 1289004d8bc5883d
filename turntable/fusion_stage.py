"""The point-fusion stage: per-view stereo depth -> fused points -> hull-aware surface.

Wires :mod:`recon.stereo`, :mod:`recon.fusion` and :mod:`recon.surface`, and
decides whether the fused surface replaces the hull mesh
(:func:`recon.surface.compare_to_hull`: the mesh that agrees better with the
confident stereo depth where the two differ).
"""

from __future__ import annotations

import logging

import numpy as np

from recon.types import FusedPoints, TableMesh, VoxelHull

log = logging.getLogger(__name__)

__all__ = ["run_fusion"]


def run_fusion(images_rgb, masks, K: np.ndarray, T_cam_table: np.ndarray, hull: VoxelHull, hull_mesh: TableMesh,
               opts, progress) -> tuple[TableMesh, FusedPoints, str]:
    """Returns (mesh to colour and export, fused points, a one-line note for the summary)."""
    from recon.fusion import fuse_depths
    from recon.meshing import finalize_mesh
    from recon.stereo import depth_maps, hull_depth_range
    from recon.surface import compare_to_hull, fused_surface

    H, W = images_rgb[0].shape[:2]
    with progress.stage("stereo") as tick:
        depth_range = hull_depth_range(hull, K, T_cam_table, (W, H), margin_mm=2.0, scale=0.5)
        depths = depth_maps(images_rgb, K, T_cam_table, depth_range, masks=masks, progress=tick)
    with progress.stage("fusion") as tick:
        fused = fuse_depths(depths, images_rgb, K, T_cam_table, progress=tick)
    if len(fused.pts_table) == 0:
        return hull_mesh, fused, "hull kept: stereo found no consistent points"
    with progress.stage("surface") as tick:
        v, f = fused_surface(fused, hull, K, T_cam_table, depths, size=(W, H), progress=tick)
        mesh = finalize_mesh(v, f, opts.max_faces)
        # judged on every other view's depth (fusion used all; a partial hold-out)
        cmp = compare_to_hull((hull_mesh.vertices_table, hull_mesh.faces), (mesh.vertices_table, mesh.faces),
                              depths[1::2], K, T_cam_table[1::2])
        detail = (f"{len(fused.pts_table)} fused points; where hull and fused surface differ "
                  f"({cmp.n_pixels} px) stereo agrees with the fused surface to {cmp.fused_err_mm:.2f} mm, "
                  f"with the hull to {cmp.hull_err_mm:.2f} mm")
    if not cmp.use_fused:
        return hull_mesh, fused, f"hull kept: {detail}"
    return mesh, fused, f"fused surface replaces the hull: {detail}"
