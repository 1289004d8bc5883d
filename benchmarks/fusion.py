"""Point fusion benchmark: hull mesh vs fused mesh, fused-point accuracy/completeness, stage time.

Usage::

    nice .venv/bin/python benchmarks/fusion.py [--data DIR] [--objects cup vase chair] [--views 36]

With ``--data DIR`` each object is read from ``DIR/<object>/`` as written by
``turntable synth`` (images/, masks/, cameras_gt.json, object_gt.ply). Without
it, scenes are ray-cast here from ``turntable.synth.objects.make_object``
(albedo texture, head-light Lambertian shading, black background, GT masks):
1280x960, f = 1600 px, camera 450 mm from the turntable axis at 30 deg
elevation, 36 views 10 deg apart.

Measures (Middlebury-style for points):
- Chamfer: symmetric mean surface distance (mm) to the GT mesh, 100k area
  samples each way, for the hull mesh (``recon.meshing.mesh_from_hull``) and
  the fused mesh as the fusion stage makes it (``recon.surface.fused_field``
  on the even views, ``recon.regions.choose_regions`` on the odd ones,
  ``supported_field``, ``mesh_from_hull``, ``clip_to_hull``).
- regions kept (of those stereo carved), bodies, watertight, and how far the
  fused mesh's farthest vertex lies outside the hull.
- accuracy: distance (mm) within which 90 % of fused points lie to the GT.
- completeness: share of GT surface samples seen by >= 2 views (front-facing,
  unoccluded) with a fused point within 1.25 mm.
- stage time: hull depth range + depth maps + fusion + surface (s).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon.carving import carve_hull  # noqa: E402
from recon.fusion import fuse_depths  # noqa: E402
from recon.meshing import clip_to_hull, hull_excess_mm, mesh_from_hull, mesh_stats  # noqa: E402
from recon.regions import choose_regions, supported_field  # noqa: E402
from recon.stereo import depth_maps, hull_depth_range, pixel_rays_table  # noqa: E402
from recon.surface import fused_field  # noqa: E402
from recon.types import VoxelHull  # noqa: E402

SIZE = (1280, 960)
FOCAL_PX = 1600.0
DIST_MM = 450.0
ELEV_DEG = 30.0


def _poses(n_views: int) -> np.ndarray:
    e = np.radians(ELEV_DEG)
    target = np.array([0.0, 50.0, 0.0])
    eye = np.array([0.0, DIST_MM * np.sin(e), -DIST_MM * np.cos(e)]) + target
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R, -R @ eye
    out = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        Ry = np.eye(4)
        Ry[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(a), np.sin(a), -np.sin(a), np.cos(a)
        out.append(T0 @ Ry)
    return np.stack(out)


def _scene_cast(mesh: trimesh.Trimesh):
    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return sc


def render_own(name: str, n_views: int, seed: int = 0):
    """Images (V, H, W, 3) uint8, masks, K, poses and the GT mesh, ray-cast here."""
    from turntable.synth.objects import make_object

    mesh = make_object(name, np.random.default_rng(seed))
    albedo = mesh.metadata.get("albedo")
    K = np.array([[FOCAL_PX, 0, (SIZE[0] - 1) / 2], [0, FOCAL_PX, (SIZE[1] - 1) / 2], [0, 0, 1.0]])
    Ts = _poses(n_views)
    sc = _scene_cast(mesh)
    fn = np.asarray(mesh.face_normals)
    imgs, masks = [], []
    for T in Ts:
        c, d = pixel_rays_table(K, T, SIZE)
        rays = np.concatenate([np.broadcast_to(c, d.shape), d], -1).astype(np.float32)
        ans = sc.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        p = c + d[hit] * t[hit, None]
        n = fn[ans["primitive_ids"].numpy()[hit]]
        v = -d[hit] / np.linalg.norm(d[hit], axis=1, keepdims=True)
        shade = 0.25 + 0.75 * np.abs(np.sum(n * v, 1))
        img = np.zeros((SIZE[1], SIZE[0], 3), np.float32)
        img[hit] = albedo(p) * shade[:, None]
        imgs.append(np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8))
        masks.append(hit)
    return np.stack(imgs), np.stack(masks), K, Ts, mesh


def load_synth(root: Path):
    """A ``turntable synth`` output directory."""
    import cv2

    from turntable.cameras_io import read_cameras

    seq = read_cameras(root / "cameras_gt.json")
    K = seq.intrinsics.K
    Ts = np.stack([f.T_cam_table for f in seq.frames])
    imgs = np.stack([cv2.cvtColor(cv2.imread(str(root / "images" / f.image)), cv2.COLOR_BGR2RGB) for f in seq.frames])
    mnames = sorted((root / "masks").iterdir())
    masks = np.stack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in mnames])
    return imgs, masks, K, Ts, trimesh.load_mesh(root / "object_gt.ply")


def chamfer(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 100_000, seed: int = 0) -> float:
    """Symmetric mean surface distance (mm)."""
    pa = trimesh.sample.sample_surface(a, n, seed=seed)[0]
    pb = trimesh.sample.sample_surface(b, n, seed=seed + 1)[0]
    da = _scene_cast(b).compute_distance(o3d.core.Tensor(pa.astype(np.float32))).numpy()
    db = _scene_cast(a).compute_distance(o3d.core.Tensor(pb.astype(np.float32))).numpy()
    return 0.5 * (float(da.mean()) + float(db.mean()))


def visible_gt_samples(gt: trimesh.Trimesh, K, Ts, n: int = 100_000, min_views: int = 2) -> np.ndarray:
    """GT surface samples that at least ``min_views`` cameras see (front-facing, unoccluded)."""
    p, fi = trimesh.sample.sample_surface(gt, n, seed=3)
    nrm = np.asarray(gt.face_normals)[fi]
    sc = _scene_cast(gt)
    seen = np.zeros(len(p), int)
    for T in Ts:
        c = -T[:3, :3].T @ T[:3, 3]
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        rays = np.concatenate([np.broadcast_to(c, d.shape), d], 1).astype(np.float32)
        t = sc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        pc = p @ T[:3, :3].T + T[:3, 3]
        uv = pc @ K.T
        inimg = (uv[:, 0] / uv[:, 2] > 0) & (uv[:, 0] / uv[:, 2] < SIZE[0]) & (uv[:, 1] / uv[:, 2] > 0) & (
            uv[:, 1] / uv[:, 2] < SIZE[1])
        seen += (np.abs(t - dist) < 0.2) & (np.sum(nrm * d, 1) < -0.1) & inimg
    return p[seen >= min_views]


def run_object(name, imgs, masks, K, Ts, gt):
    hull = carve_hull(masks, K, Ts)
    hull_tm = mesh_from_hull(hull)
    t0 = time.perf_counter()
    near, far = hull_depth_range(hull, K, Ts, SIZE, margin_mm=2.0, scale=0.5)
    t1 = time.perf_counter()
    dms = depth_maps(imgs, K, Ts, (near, far), masks=masks)
    t2 = time.perf_counter()
    pts = fuse_depths(dms, imgs, K, Ts)
    t3 = time.perf_counter()
    F = fused_field(pts, hull, K, Ts[0::2], dms[0::2], size=SIZE)  # the fusion stage: even views carve,
    choice = choose_regions(hull, F, dms[1::2], K, Ts[1::2], masks[1::2])  # odd views judge each region
    G = supported_field(hull.values, choice.values)
    fused_tm = clip_to_hull(mesh_from_hull(VoxelHull(G, hull.origin_table, hull.voxel_mm)), hull)
    t4 = time.perf_counter()
    st = mesh_stats(fused_tm)
    hull_mesh_t = trimesh.Trimesh(hull_tm.vertices_table, hull_tm.faces, process=False)
    fused_mesh_t = trimesh.Trimesh(fused_tm.vertices_table, fused_tm.faces, process=False)
    d_pts = _scene_cast(gt).compute_distance(o3d.core.Tensor(pts.pts_table.astype(np.float32))).numpy()
    vis = visible_gt_samples(gt, K, Ts)
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.pts_table)))
    comp = np.mean([tree.search_knn_vector_3d(q, 1)[2][0] <= 1.25 ** 2 for q in vis]) if len(pts.pts_table) else 0.0
    return dict(name=name, ch_hull=chamfer(hull_mesh_t, gt), ch_fused=chamfer(fused_mesh_t, gt),
                acc90=float(np.percentile(d_pts, 90)) if len(d_pts) else float("nan"), comp=float(comp),
                n_pts=len(pts.pts_table), t_range=t1 - t0, t_depth=t2 - t1, t_fuse=t3 - t2, t_surf=t4 - t3,
                kept=f"{choice.n_kept}/{choice.n_regions}", bodies=st.n_bodies, watertight=st.watertight,
                outside=hull_excess_mm(fused_tm, hull), voxel=hull.voxel_mm)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="root of `turntable synth` outputs, one folder per object")
    ap.add_argument("--objects", nargs="+", default=["cup", "vase", "chair"])
    ap.add_argument("--views", type=int, default=36)
    args = ap.parse_args()
    print(f"# fusion benchmark — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
          f"{platform.machine()} {platform.processor() or ''}, {os.cpu_count()} CPUs, "
          f"python {platform.python_version()}")
    print()
    print("| object | hull voxel mm | Chamfer hull mm | Chamfer fused mm | fused/hull | pts acc90 mm | "
          "completeness @1.25 mm | points | range s | depth s | fuse s | surface s | stage s | regions kept | "
          "bodies | watertight | outside hull mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.objects:
        data = load_synth(args.data / name) if args.data else render_own(name, args.views)
        r = run_object(name, *data)
        stage = r["t_range"] + r["t_depth"] + r["t_fuse"] + r["t_surf"]
        print(f"| {name} | {r['voxel']:.2f} | {r['ch_hull']:.3f} | {r['ch_fused']:.3f} | "
              f"{r['ch_fused'] / r['ch_hull']:.2f} | {r['acc90']:.3f} | {100 * r['comp']:.1f} % | {r['n_pts']} | "
              f"{r['t_range']:.1f} | {r['t_depth']:.1f} | {r['t_fuse']:.1f} | {r['t_surf']:.1f} | {stage:.1f} | "
              f"{r['kept']} | {r['bodies']} | {r['watertight']} | {r['outside']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
