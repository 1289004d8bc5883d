"""Speed and accuracy of hull meshing and vertex colouring on synthetic hulls.

Run: ``nice .venv/bin/python benchmarks/meshing_colorize.py [--n 256]``. Prints a markdown table.
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
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run without installing

from calib import camera
from recon.colorize import color_vertices
from recon.meshing import mesh_from_hull, mesh_stats
from recon.types import VoxelHull


def vase_hull(n: int) -> tuple[VoxelHull, float]:
    """A sphere of radius 0.4 n voxels (exact signed distance) and its true volume, mm³."""
    voxel = 200.0 / n
    ax = (np.arange(n) - (n - 1) / 2) * voxel
    X, Y, Z = np.meshgrid(ax, ax + 100.0, ax, indexing="ij")
    R = 0.4 * n * voxel
    values = (R - np.sqrt(X**2 + (Y - 100.0) ** 2 + Z**2)).astype(np.float32)
    return VoxelHull(values, np.array([ax[0], ax[0] + 100.0, ax[0]]), voxel), 4 / 3 * np.pi * R**3


def look_at(c, target=(0.0, 100.0, 0.0)):
    return camera.look_at(c, target)


def render(mesh, face_rgb, K, T, W, H):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices_table.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(K).T @ T[:3, :3]
    c = -T[:3, :3].T @ T[:3, 3]
    ids = scene.cast_rays(o3d.core.Tensor(np.hstack([np.broadcast_to(c, d.shape), d]).astype(np.float32)))
    ids = ids["primitive_ids"].numpy().astype(np.int64)
    img = np.zeros((H * W, 3), np.uint8)
    hit = ids != scene.INVALID_ID
    img[hit] = face_rgb[ids[hit]]
    return img.reshape(H, W, 3)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--max-faces", type=int, default=100_000)
    ap.add_argument("--views", type=int, default=36)
    args = ap.parse_args()
    print(f"meshing + colouring, {datetime.date.today()}, {platform.platform()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs\n")
    print("| hull | MC faces | faces out | watertight | vol err | |r-R| max (voxel) | mesh s "
          f"| colour {args.views}x1280x960 s | colour err p99 |")
    print("|---|---|---|---|---|---|---|---|---|")
    W, H = 1280, 960
    K = np.array([[1500.0, 0, (W - 1) / 2], [0, 1500.0, (H - 1) / 2], [0, 0, 1]])
    for n in args.n:
        hull, vol = vase_hull(n)
        t0 = time.perf_counter()
        raw = mesh_from_hull(hull, max_faces=10**8, smooth_iters=0)
        t1 = time.perf_counter()
        mesh = mesh_from_hull(hull, max_faces=args.max_faces, smooth_iters=10)
        t2 = time.perf_counter()
        st = mesh_stats(mesh)
        R = 0.4 * n * hull.voxel_mm
        r_err = np.abs(np.linalg.norm(mesh.vertices_table - [0, 100, 0], axis=1) - R).max() / hull.voxel_mm
        tm = trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False)
        c = tm.triangles_center - [0, 100, 0]
        pattern = np.array([[200, 40, 40], [40, 180, 60], [50, 60, 210], [230, 210, 30]], np.uint8)
        face_rgb = pattern[(c[:, 0] > 0) * 1 + (c[:, 2] > 0) * 2]
        poses = [look_at(500.0 * np.array([np.cos(a) * 0.9, 0.45, np.sin(a) * 0.9]) + [0, 0, 0])
                 for a in np.linspace(0, 2 * np.pi, args.views, endpoint=False)]
        images = [render(mesh, face_rgb, K, T, W, H) for T in poses]
        t3 = time.perf_counter()
        out = color_vertices(mesh, images, K, np.array(poses))
        t4 = time.perf_counter()
        p = mesh.vertices_table - [0, 100, 0]
        far = (np.minimum(np.abs(p[:, 0]), np.abs(p[:, 2])) > 0.15 * R) & (p[:, 1] > -0.3 * R)
        truth = pattern[(p[far, 0] > 0) * 1 + (p[far, 2] > 0) * 2].astype(int)
        err = np.percentile(np.abs(out.colors_rgb[far].astype(int) - truth).max(axis=1), 99)
        print(f"| {n}³ | {len(raw.faces)} | {st.n_faces} | {st.watertight} | {st.volume_mm3 / vol - 1:+.2%} "
              f"| {r_err:.3f} | {t2 - t1:.2f} (raw {t1 - t0:.2f}) | {t4 - t3:.2f} | {err:.0f} |")


if __name__ == "__main__":
    main()
