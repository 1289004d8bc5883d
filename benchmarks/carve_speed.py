"""Visual-hull carving: recon.carving.carve_hull vs open3d VoxelGrid.carve_silhouette.

Scene: a vase-like body of revolution (analytic inside test = ground truth),
off the turntable axis; 36 turntable cameras at 450 mm, 30 deg elevation,
f = 1500 px, 1280 x 960; exact masks by ray casting its mesh with open3d.
Both carvers get the same masks, cameras and voxel grid (the one carve_hull
chooses for resolution 256). Volume IoU of each against the ground-truth
occupancy at the voxel centres. Prints a markdown table.

Run: ``nice .venv/bin/python benchmarks/carve_speed.py [--resolution 256] [--no-open3d]``
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from recon.carving import carve_hull  # noqa: E402

W, H, F_PX = 1280, 960, 1500.0
K = np.array([[F_PX, 0.0, (W - 1) / 2], [0.0, F_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])
HEIGHT_MM = 110.0
OFFSET_TABLE = np.array([8.0, 0.0, -5.0])


def radius_at(y_mm: np.ndarray) -> np.ndarray:
    """Vase profile radius (mm) at height y: a belly, a concave neck and a lip."""
    t = np.asarray(y_mm) / HEIGHT_MM
    return 18.0 + 16.0 * np.sin(np.pi * np.clip(t, 0, 1) * 1.15) ** 2 - 6.0 * np.exp(-((t - 0.85) / 0.06) ** 2)


def vase_mesh(n_seg: int = 256, n_rings: int = 220) -> tuple[np.ndarray, np.ndarray]:
    """Closed triangle mesh (table frame, mm) of the vase: vertices (N, 3), faces (M, 3)."""
    ys = np.linspace(0.0, HEIGHT_MM, n_rings)
    th = np.linspace(0.0, 2 * np.pi, n_seg, endpoint=False)
    r = radius_at(ys)[:, None]
    ring = np.stack([r * np.cos(th), np.broadcast_to(ys[:, None], r.shape * np.array([1, n_seg])),
                     r * np.sin(th)], -1).reshape(-1, 3)
    verts = np.vstack([ring, [[0, 0, 0], [0, HEIGHT_MM, 0]]]) + OFFSET_TABLE
    i, j = np.meshgrid(np.arange(n_rings - 1), np.arange(n_seg), indexing="ij")
    a, b = i * n_seg + j, i * n_seg + (j + 1) % n_seg
    c, d = a + n_seg, b + n_seg
    side = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    bot, top = len(ring), len(ring) + 1
    jj = np.arange(n_seg)
    caps = np.concatenate([np.stack([np.full(n_seg, bot), jj, (jj + 1) % n_seg], -1),
                           np.stack([np.full(n_seg, top), (n_rings - 1) * n_seg + (jj + 1) % n_seg,
                                     (n_rings - 1) * n_seg + jj], -1)])
    return verts, np.concatenate([side, caps])


def inside_gt(pts_table: np.ndarray) -> np.ndarray:
    p = pts_table - OFFSET_TABLE
    return (p[:, 1] >= 0) & (p[:, 1] <= HEIGHT_MM) & (np.hypot(p[:, 0], p[:, 2]) <= radius_at(p[:, 1]))


def turntable_cameras(n: int, distance_mm=450.0, elevation_deg=30.0, look_at=(0.0, 50.0, 0.0)) -> np.ndarray:
    e, target = np.radians(elevation_deg), np.asarray(look_at)
    Ts = []
    for th in np.linspace(0, 2 * np.pi, n, endpoint=False):
        c = distance_mm * np.array([np.cos(th) * np.cos(e), np.sin(e), np.sin(th) * np.cos(e)])
        z = (target - c) / np.linalg.norm(target - c)
        y = -(np.array([0.0, 1.0, 0.0]) - z[1] * z)
        y /= np.linalg.norm(y)
        R = np.stack([np.cross(y, z), y, z])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ c
        Ts.append(T)
    return np.array(Ts)


def render_masks(verts, faces, Ts) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    K_o3d = K.copy()
    K_o3d[:2, 2] += 0.5  # open3d's rays pass through (u + 0.5, v + 0.5): shift to pixel centres
    out = []
    for T in Ts:
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(o3d.core.Tensor(K_o3d), o3d.core.Tensor(T), W, H)
        out.append(np.isfinite(scene.cast_rays(rays)["t_hit"].numpy()))
    return np.array(out)


def carve_open3d(masks, Ts, origin_centre, voxel, dims) -> np.ndarray:
    """Occupancy (dims) bool from open3d's carve_silhouette on the same grid."""
    lo = origin_centre - 0.5 * voxel
    ext = dims * voxel - 1e-3 * voxel
    grid = o3d.geometry.VoxelGrid.create_dense(lo, np.zeros(3), voxel, *ext)
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    for m, T in zip(masks, Ts, strict=True):
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic, params.extrinsic = intr, T
        grid.carve_silhouette(o3d.geometry.Image(m.astype(np.float32)), params, keep_voxels_outside_image=False)
    idx = np.array([v.grid_index for v in grid.get_voxels()]).reshape(-1, 3)
    occ = np.zeros(dims, bool)
    if len(idx):
        occ[tuple(idx.T)] = True
    if not np.allclose(np.asarray(grid.origin) + 0.5 * voxel, origin_centre):  # voxel i centre: origin + (i + 1/2) h
        raise RuntimeError("open3d grid is not aligned with carve_hull's grid")
    return occ


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--no-open3d", action="store_true", help="skip the (slow) open3d baseline")
    args = ap.parse_args()

    verts, faces = vase_mesh()
    Ts = turntable_cameras(args.views)
    masks = render_masks(verts, faces, Ts)
    rows = []
    for k in (0, 1):
        t0 = time.perf_counter()
        hull = carve_hull(masks, K, Ts, radius_mm=80.0, resolution=args.resolution, max_rejections=k)
        rows.append((f"carve_hull (max_rejections={k})", time.perf_counter() - t0, hull.values > 0))
    dims = np.array(hull.values.shape)
    gt = inside_gt(hull.centres_table(np.indices(dims).reshape(3, -1).T)).reshape(dims)
    if not args.no_open3d:
        t0 = time.perf_counter()
        occ = carve_open3d(masks, Ts, hull.origin_table, hull.voxel_mm, dims)
        rows.append(("open3d VoxelGrid.carve_silhouette", time.perf_counter() - t0, occ))

    print(f"## Visual-hull carving — {datetime.date.today()}, {platform.platform()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs\n")
    print(f"{args.views} views of {W}x{H} masks, grid {dims[0]}x{dims[1]}x{dims[2]} "
          f"({hull.voxel_mm:.3f} mm voxels), vase {HEIGHT_MM:.0f} mm tall; "
          f"IoU against the analytic shape at voxel centres\n")
    base = rows[-1][1]
    print("| method | time (s) | speed-up vs open3d | volume IoU vs GT |")
    print("|---|---:|---:|---:|")
    for name, dt, occ in rows:
        ratio = f"{base / dt:.1f}x" if not args.no_open3d else "n/a"
        print(f"| {name} | {dt:.2f} | {ratio} | {iou(occ, gt):.4f} |")


if __name__ == "__main__":
    main()
