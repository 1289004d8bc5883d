"""Geometric fusion of per-view depth maps into one coloured, oriented point cloud.

As in COLMAP's stereo fusion, a pixel of view ``r`` with depth ``z_r`` gives
the table point ``X = T_table_r (z_r K^-1 p)``. Projected into another view
``j`` (``x_j ~ K T_j_table X``, depth ``z_X``) it *agrees* with ``j`` when

    |D_j(x_j) - z_X| <= tol_mm   and   angle(n_r(p), n_j(x_j)) <= max_normal_deg,

``D_j`` the depth map and ``n`` the normals from depth-map gradients. A pixel
survives when at least ``min_views`` views (itself included) agree; its point
is the mean of the agreeing views' back-projections (noise averages down), its
normal their mean, oriented towards the cameras. Surviving points of all views
are merged on a ``voxel_mm`` grid (open3d voxel down-sampling averages
positions, normals and colours).

Everything runs on every ``stride``-th pixel: the sweep in :mod:`recon.stereo`
is at half resolution, so ``stride=2`` loses nothing and quarters the work.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from .stereo import select_neighbours
from .types import DepthMap, FusedPoints

__all__ = ["FusionOptions", "fuse_depths", "ViewSamples", "view_samples"]


@dataclass(frozen=True)
class FusionOptions:
    """Settings of :func:`fuse_depths`.

    Attributes
    ----------
    min_views : int
        Views (the pixel's own included) that must agree.
    tol_mm, max_normal_deg : float
        Agreement in depth (mm, along the other view's axis) and normal.
    min_confidence : float
        Depth pixels below this confidence are ignored.
    check_neighbours : int
        Each pixel is checked in the ``2 * check_neighbours`` angularly
        nearest views.
    stride : int
        Pixel step of the check (2 matches a half-resolution sweep).
    voxel_mm : float
        Merge grid; 0 keeps every surviving pixel.
    """

    min_views: int = 3
    tol_mm: float = 1.5
    max_normal_deg: float = 30.0
    min_confidence: float = 0.2
    check_neighbours: int = 4
    stride: int = 2
    voxel_mm: float = 0.5


@dataclass(frozen=True)
class ViewSamples:
    """One view's depth map sampled on every ``stride``-th pixel.

    Attributes
    ----------
    depth_mm : (h, w) float32
        z-depth, 0 where unknown or not confident enough.
    normals_table : (h, w, 3) float32
        Unit normals in the table frame, towards the camera; NaN where unknown.
    K_sub : (3, 3) float64
        Intrinsics of the sub-sampled grid.
    T_cam_table : (4, 4) float64
    """

    depth_mm: np.ndarray
    normals_table: np.ndarray
    K_sub: np.ndarray
    T_cam_table: np.ndarray


def view_samples(dm: DepthMap, K: np.ndarray, T_cam_table: np.ndarray, stride: int,
                 min_confidence: float, max_jump: float = 0.02) -> ViewSamples:
    """Sub-sample a depth map and estimate normals from its gradients.

    Normals come from central differences of the back-projected points; a
    neighbour whose depth differs by more than ``max_jump`` (relative) is a
    depth edge and leaves the normal unknown.
    """
    z = np.where(dm.confidence >= min_confidence, dm.depth_mm, 0.0)[::stride, ::stride].astype(np.float32)
    K_sub = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ np.asarray(K, float)
    h, w = z.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    Ki = np.linalg.inv(K_sub).astype(np.float32)
    P = np.stack([u, v, np.ones_like(u)], -1) @ Ki.T * z[..., None]
    n = np.full((h, w, 3), np.nan, np.float32)
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    zc = z[1:-1, 1:-1]
    ok = (zc > 0) & (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0) & (z[:-2, 1:-1] > 0)
    for a, b in ((z[1:-1, 2:], z[1:-1, :-2]), (z[2:, 1:-1], z[:-2, 1:-1])):
        ok &= np.abs(a - b) <= 2 * max_jump * np.maximum(zc, 1e-6)
    c = np.cross(dx, dy)
    c /= np.linalg.norm(c, axis=-1, keepdims=True) + 1e-12
    c *= -np.sign(np.sum(c * P[1:-1, 1:-1], -1, keepdims=True))  # towards the camera (P is the view ray)
    R = np.asarray(T_cam_table, float)[:3, :3].astype(np.float32)
    n[1:-1, 1:-1] = np.where(ok[..., None], c @ R, np.nan)  # rows: R^T c
    return ViewSamples(depth_mm=z, normals_table=n, K_sub=K_sub, T_cam_table=np.asarray(T_cam_table, float))


def _back_project(vs: ViewSamples, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    z = vs.depth_mm[ys, xs].astype(np.float64)
    pix = np.stack([xs, ys, np.ones_like(xs)], -1).astype(np.float64)
    p_cam = pix @ np.linalg.inv(vs.K_sub).T * z[:, None]
    R, t = vs.T_cam_table[:3, :3], vs.T_cam_table[:3, 3]
    return (p_cam - t) @ R


def _agree(pts_table, normals, vs: ViewSamples, tol_mm: float, cos_max: float):
    """Which points view ``vs`` confirms, and its own back-projection of them."""
    R, t = vs.T_cam_table[:3, :3], vs.T_cam_table[:3, 3]
    pc = pts_table @ R.T + t
    uvw = pc @ vs.K_sub.T
    zp = uvw[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.rint(uvw[:, 0] / zp)
        y = np.rint(uvw[:, 1] / zp)
    h, w = vs.depth_mm.shape
    inb = (zp > 0) & (x >= 0) & (y >= 0) & (x < w) & (y < h)
    xi = np.where(inb, x, 0).astype(np.intp)
    yi = np.where(inb, y, 0).astype(np.intp)
    dj = vs.depth_mm[yi, xi]
    nj = vs.normals_table[yi, xi]
    ok = inb & (dj > 0) & (np.abs(dj - zp) <= tol_mm)
    ok &= np.nan_to_num(np.sum(nj * normals, -1), nan=-1.0) >= cos_max
    return ok, yi, xi


def _fuse_view(r, samples, check, images_rgb, o: FusionOptions):
    """View ``r``'s pixels that ``o.min_views`` views agree on: (points, unit normals, rgb), each (n, 3); or None."""
    stride, min_views, tol_mm = o.stride, o.min_views, o.tol_mm
    cos_max = float(np.cos(np.radians(o.max_normal_deg)))
    vs = samples[r]
    ys, xs = np.nonzero((vs.depth_mm > 0) & np.isfinite(vs.normals_table[..., 0]))
    if len(ys) == 0:
        return None
    pts = _back_project(vs, ys, xs)
    nrm = vs.normals_table[ys, xs].astype(np.float64)
    acc_p, acc_n, count = pts.copy(), nrm.copy(), np.ones(len(ys), np.int32)
    for j in check:
        ok, yj, xj = _agree(pts, nrm, samples[j], tol_mm, cos_max)
        if ok.any():
            acc_p[ok] += _back_project(samples[j], yj[ok], xj[ok])
            acc_n[ok] += samples[j].normals_table[yj[ok], xj[ok]]
            count[ok] += 1
    keep = count >= min_views
    img = np.asarray(images_rgb[r])
    rgb = img[ys[keep] * stride, xs[keep] * stride]
    if rgb.ndim == 1:
        rgb = np.repeat(rgb[:, None], 3, 1)
    n = acc_n[keep]
    return acc_p[keep] / count[keep, None], n / np.linalg.norm(n, axis=1, keepdims=True), rgb[:, :3]


def fuse_depths(depths: Sequence[DepthMap], images_rgb: Sequence[np.ndarray], K: np.ndarray,
                T_cam_table: Sequence[np.ndarray] | np.ndarray, *, options: FusionOptions | None = None,
                progress: Callable[[int, int], None] | None = None, **overrides) -> FusedPoints:
    """Consistency-checked, merged point cloud of all depth maps.

    Parameters
    ----------
    depths : sequence of V DepthMap, (H, W)
        From :func:`recon.stereo.depth_maps`, view ``i`` for pose ``i``.
    images_rgb : sequence of V (H, W, 3) uint8
        Colours.
    K : (3, 3) float64
        Intrinsics of the (H, W) images.
    T_cam_table : (V, 4, 4) float64
        Poses, table mm -> camera mm.
    options : FusionOptions, optional
        The check's settings; default ``FusionOptions()``.
    **overrides
        Fields of :class:`FusionOptions` by name (``min_views=2``), replacing
        those of ``options``.

    Returns
    -------
    FusedPoints
        Table-frame points (mm), unit normals towards the observing cameras,
        colours.
    """
    o = replace(options or FusionOptions(), **overrides)
    Ts = np.asarray(T_cam_table, dtype=np.float64).reshape(-1, 4, 4)
    if len(depths) != len(Ts) or len(images_rgb) != len(Ts):
        raise ValueError(f"{len(depths)} depth maps, {len(images_rgb)} images, {len(Ts)} poses")
    if o.min_views < 1 or o.stride < 1:
        raise ValueError("min_views and stride must be >= 1")
    samples = [view_samples(d, K, T, o.stride, o.min_confidence) for d, T in zip(depths, Ts, strict=True)]
    check = select_neighbours(Ts, o.check_neighbours, min_angle_deg=0.0)
    parts = []
    for r in range(len(Ts)):
        res = _fuse_view(r, samples, check[r], images_rgb, o)
        if res is not None and len(res[0]):
            parts.append(res)
        if progress is not None:
            progress(r + 1, len(Ts))
    if not parts:
        return FusedPoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    pts = np.concatenate([p[0] for p in parts])
    nrm = np.concatenate([p[1] for p in parts])
    rgb = np.concatenate([p[2] for p in parts])
    if o.voxel_mm > 0:
        pts, nrm, rgb = _voxel_merge(pts, nrm, rgb, o.voxel_mm)
    return FusedPoints(pts_table=pts, normals_table=nrm, colors_rgb=rgb)


def _voxel_merge(pts, nrm, rgb, voxel_mm):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(nrm)
    pc.colors = o3d.utility.Vector3dVector(rgb.astype(np.float64) / 255.0)
    pc = pc.voxel_down_sample(voxel_mm)
    n = np.asarray(pc.normals)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    rgb = np.clip(np.rint(np.asarray(pc.colors) * 255.0), 0, 255).astype(np.uint8)
    return np.asarray(pc.points), n, rgb
