"""Hull -> mesh -> colours -> export on data/sample with ground-truth cameras and masks.

Run: ``nice .venv/bin/python benchmarks/sample_mesh.py [--resolution 128 256]``.
Compares the coloured hull mesh with ``object_gt.ply`` (same table frame, mm):
volume and surface distance both ways (sampled, via open3d's ray caster), and
the time of each stage. (No colour error: the sample's images are shaded by a
light fixed in the world while the object turns, so no single vertex colour
matches the albedo in object_gt.ply.) Prints a markdown table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run without installing

from recon.carving import carve_hull
from recon.colorize import color_vertices
from recon.export import export_colmap, export_mesh, export_nerfstudio
from recon.meshing import mesh_from_hull, mesh_stats

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample"


def load_sample():
    cams = json.loads((SAMPLE / "cameras_gt.json").read_text())
    K = np.array(cams["intrinsics"]["K"])
    names = [f["image"] for f in cams["frames"]]
    Ts = np.array([f["T_cam_table"] for f in cams["frames"]])
    images = [cv2.cvtColor(cv2.imread(str(SAMPLE / n)), cv2.COLOR_BGR2RGB) for n in names]
    masks = np.array([cv2.imread(str(SAMPLE / "masks" / (Path(n).stem + ".png")), cv2.IMREAD_GRAYSCALE) > 0
                      for n in names])
    return cams, K, names, Ts, images, masks


def distances(src_pts, mesh_v, mesh_f):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh_v.astype(np.float32)), o3d.core.Tensor(mesh_f.astype(np.uint32)))
    q = scene.compute_closest_points(o3d.core.Tensor(src_pts.astype(np.float32)))
    return np.linalg.norm(q["points"].numpy() - src_pts, axis=1), q["primitive_ids"].numpy()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--resolution", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--max-faces", type=int, default=100_000)
    args = ap.parse_args()
    print(f"data/sample hull mesh vs object_gt.ply, {datetime.date.today()}, {platform.platform()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}\n")
    cams, K, names, Ts, images, masks = load_sample()
    gt = trimesh.load(SAMPLE / "object_gt.ply", process=False)
    gt_pts, _ = trimesh.sample.sample_surface(gt, 20000, seed=0)
    print("| resolution | voxel mm | faces | watertight | vol / GT | GT→mesh mean / p95 mm "
          "| mesh→GT mean / p95 mm | carve s | mesh s | colour s | export s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for res in args.resolution:
        t0 = time.perf_counter()
        hull = carve_hull(masks, K, Ts, resolution=res)
        t1 = time.perf_counter()
        mesh = mesh_from_hull(hull, max_faces=args.max_faces)
        t2 = time.perf_counter()
        mesh = color_vertices(mesh, images, K, Ts, masks=masks)
        t3 = time.perf_counter()
        with tempfile.TemporaryDirectory() as d:
            export_mesh(mesh, d)
            frames = list(zip(names, Ts, strict=True))
            export_colmap(K, 1280, 960, frames, Path(d) / "colmap")
            export_nerfstudio(K, 1280, 960, frames, d, ply_file_path="model.ply")
        t4 = time.perf_counter()
        st = mesh_stats(mesh)
        d_gt, _ = distances(gt_pts, mesh.vertices_table, mesh.faces)
        d_mesh, _ = distances(mesh.vertices_table, np.asarray(gt.vertices), np.asarray(gt.faces))
        print(f"| {res} | {hull.voxel_mm:.2f} | {st.n_faces} | {st.watertight} | {st.volume_mm3 / gt.volume:.3f} "
              f"| {d_gt.mean():.2f} / {np.percentile(d_gt, 95):.2f} "
              f"| {d_mesh.mean():.2f} / {np.percentile(d_mesh, 95):.2f} "
              f"| {t1 - t0:.1f} | {t2 - t1:.1f} | {t3 - t2:.1f} | {t4 - t3:.1f} |")


if __name__ == "__main__":
    main()
