"""Rays from the cameras and ray casting against a table-frame triangle mesh.

A pixel ``p = (u, v, 1)`` of a camera with pose ``T_cam_table = [R | t]``
looks along the table-frame ray

    X(s) = C + s R^T K^-1 p,      C = -R^T t,

whose camera-frame z is ``s``: a hit at ``s = t_hit`` is at z-depth ``t_hit``
mm. Casting uses open3d's ``RaycastingScene`` (Embree), built once per mesh by
:func:`raycasting_scene`; :func:`first_hits` casts an (N, 6) array of rays
(origin, direction) and returns the ray parameter of the first hit, ``inf``
on a miss.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["pixel_rays_table", "raycasting_scene", "first_hits", "render_depth"]


def pixel_rays_table(K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and per-pixel ray directions (H, W, 3) in the table frame.

    Directions are scaled so that their camera-frame z is 1: a distance ``t``
    along them is the z-depth ``t`` mm.
    """
    W, H = int(size[0]), int(size[1])
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    d_cam = pix @ np.linalg.inv(K).T
    R = T_cam_table[:3, :3]
    centre = -R.T @ T_cam_table[:3, 3]
    return centre, d_cam @ R  # rows: R^T d


def raycasting_scene(vertices_table: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An open3d ray-casting scene holding one triangle mesh.

    Parameters
    ----------
    vertices_table : (N, 3) float, mm
        Cast as float32.
    faces : (M, 3) int
        Vertex indices, cast as uint32.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    # open3d's stubs make Tensor's dtype and device required; they are optional
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices_table).astype(np.float32)),  # type: ignore[call-overload]
                        o3d.core.Tensor(np.asarray(faces).astype(np.uint32)))  # type: ignore[call-overload]
    return scene


def first_hits(scene: o3d.t.geometry.RaycastingScene, rays: np.ndarray) -> np.ndarray:
    """Ray parameter ``t_hit`` (...) float32 of each ray's first hit, ``inf`` where it misses.

    ``rays`` (..., 6) float32: origin (3) and direction (3), table frame; the
    hit lies at ``origin + t_hit * direction``.
    """
    import open3d as o3d

    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # type: ignore[call-overload]  # as above


def render_depth(vertices_table: np.ndarray, faces: np.ndarray, K: np.ndarray, T_cam_table: np.ndarray,
                 size: tuple[int, int]) -> np.ndarray:
    """z-depth image (H, W) float32 (mm, camera frame) of a mesh; 0 where a pixel's ray misses it."""
    centre, dirs = pixel_rays_table(K, T_cam_table, size)
    rays = np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], -1).astype(np.float32)
    t = first_hits(raycasting_scene(vertices_table, faces), rays)
    return np.where(np.isfinite(t), t, 0.0)
