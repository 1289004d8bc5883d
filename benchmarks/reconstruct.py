"""End to end on rendered turntable sequences: silhouettes, hull mesh, fused mesh, time.

For each object x backdrop (``turntable synth``, 36 frames 1280x960, JPEG 95,
seeded; renders cached in ``--cache``) it runs ``turntable reconstruct`` as a
user would — automatic cameras and silhouettes, 256^3 — first with
``--no-fusion`` (the visual-hull mesh), then again in the same OUT with fusion
(cameras, silhouettes and hull reused). It reports the mean silhouette IoU
against the ground-truth masks, the focal-length error, the symmetric mean
Chamfer distance of each ``model.glb`` to ``object_gt.ply`` (absolute and in %
of the object's bounding-box diagonal), which mesh fusion chose, and the time
of every stage.

Bars (issues 4 and 5): mean IoU >= 0.97 across backdrops; hull Chamfer <= 1 %
of the diagonal (convex and thin-part objects); fused <= 50 % of the hull's on
the concave object, <= 110 % on the others; end to end <= 30 s (hull), fusion
stage <= 60 s; fused points accuracy90 <= 0.5 mm, completeness >= 90 % (convex object).

    .venv/bin/python benchmarks/reconstruct.py [--objects vase chair cup] [--backdrops dark light clutter]
"""

from __future__ import annotations

import argparse
import datetime
import io
import json
import os
import platform
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import redirect_stdout
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _render(args):
    from turntable.synth import SynthOptions, make_sequence

    folder, obj, backdrop, seed = args
    if not (Path(folder) / "cameras_gt.json").exists():
        make_sequence(folder, SynthOptions(object=obj, backdrop=backdrop, seed=seed), overwrite=True)
    return folder


def _chamfer(glb: Path, gt_ply: Path) -> tuple[float, float]:
    import trimesh
    from scipy.spatial import cKDTree

    m = trimesh.load(glb, force="mesh", skip_materials=True)
    gt = trimesh.load(gt_ply)
    a, b = m.sample(30000, seed=0) * 1000.0, gt.sample(30000, seed=0)
    ch = 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())
    return float(ch), float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))


def _points_quality(points_ply: Path, scene: Path) -> tuple[float, float]:
    """Middlebury-style (accuracy90 mm, completeness %) of the fused points.

    Accuracy: 90th percentile of the points' distance to the true surface.
    Completeness: share of true-surface samples that some camera sees
    (facing it, unoccluded) lying within 1.25 mm of a fused point.
    """
    import open3d as o3d
    import trimesh
    from scipy.spatial import cKDTree

    from calib.camera import camera_centre_table
    from turntable.cameras_io import read_cameras

    if not points_ply.exists():
        return float("nan"), float("nan")
    gt = trimesh.load(scene / "object_gt.ply")
    P = np.asarray(o3d.io.read_point_cloud(str(points_ply)).points)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(np.asarray(gt.vertices, np.float32), np.asarray(gt.faces, np.uint32))
    Q = P[np.random.default_rng(0).choice(len(P), min(len(P), 30000), replace=False)].astype(np.float32)
    acc90 = float(np.percentile(rc.compute_distance(o3d.core.Tensor(Q)).numpy(), 90))
    S, fi = trimesh.sample.sample_surface(gt, 20000, seed=0)
    N = gt.face_normals[fi]
    seen = np.zeros(len(S), bool)
    for f in read_cameras(scene / "cameras_gt.json").frames:
        C = camera_centre_table(f.T_cam_table)
        d = S - C
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        rays = np.hstack([np.repeat(C[None], len(S), 0), d]).astype(np.float32)
        t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        seen |= ((N * -d).sum(1) > 0.1) & (t > dist - 0.05)
    dc, _ = cKDTree(P).query(S[seen])
    return acc90, float(100 * np.mean(dc < 1.25))


def _iou(out: Path, scene: Path) -> float:
    z = np.load(out / ".turntable" / "silhouettes.npz")
    names = sorted(p.name for p in (scene / "images").iterdir())
    ious = []
    for m, n in zip(z["masks"], names, strict=True):
        g = cv2.imread(str(scene / "masks" / (Path(n).stem + ".png")), cv2.IMREAD_GRAYSCALE) > 127
        ious.append((m & g).sum() / max((m | g).sum(), 1))
    return float(np.mean(ious))


def _run(scene: Path, out: Path, extra: list[str]) -> dict:
    from turntable.cli import main

    buf = io.StringIO()
    with redirect_stdout(buf):
        code = main(["reconstruct", str(scene / "images"), "--r-outer", "80", "--r-inner", "50", "--stroke", "3",
                     "--out", str(out), "--quiet", *extra])
    if code not in (0, 1):
        raise RuntimeError(f"reconstruct failed on {scene} ({code})")
    return json.loads((out / "summary.json").read_text())


def main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", nargs="+", default=["vase", "chair", "cup"])
    p.add_argument("--backdrops", nargs="+", default=["dark", "light", "clutter"])
    p.add_argument("--cup-backdrops", nargs="+", default=["dark"], help="backdrops for the concave object")
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--cache", default="/tmp/turntable_bench_reconstruct")
    a = p.parse_args(argv)
    cache = Path(a.cache)
    jobs = []
    for obj in a.objects:
        for bd in (a.cup_backdrops if obj == "cup" else a.backdrops):
            jobs.append((str(cache / f"{obj}_{bd}"), obj, bd, a.seed))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(_render, jobs))
    t_render = time.perf_counter() - t0
    from turntable.cameras_io import read_cameras

    print(f"## End to end on rendered sequences — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
          f"{platform.machine()} {platform.platform()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}\n")
    print(f"36 frames 1280x960 JPEG 95 per sequence, seed {a.seed}, 256^3, automatic cameras and silhouettes "
          f"(renders: {t_render:.0f} s, cached in {cache}).\n")
    print("| sequence | IoU mean | f err % | hull Chamfer mm (% diag) | fused Chamfer mm (% diag) | fused/hull | "
          "chosen | points acc90 mm | completeness % | hull run s | fusion stage s | stages (hull run) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for folder, _obj, _bd, _ in jobs:
        scene = Path(folder)
        out = cache / "out" / scene.name
        shutil.rmtree(out, ignore_errors=True)
        s1 = _run(scene, out, ["--no-fusion"])
        hull_glb = out / "model_hull.glb"
        shutil.copy(out / "model.glb", hull_glb)
        s2 = _run(scene, out, [])
        gt = read_cameras(scene / "cameras_gt.json")
        f_err = 100 * (s1["focal_px"] / gt.intrinsics.focal_px - 1)
        ch_h, diag = _chamfer(hull_glb, scene / "object_gt.ply")
        ch_f, _ = _chamfer(out / "model.glb", scene / "object_gt.ply")
        t1 = s1["time_s"]
        fusion_s = sum(s2["time_s"].get(k, 0.0) for k in ("stereo", "fusion", "surface"))
        chosen = "fused" if s2["fusion"].startswith("fused") else "hull"
        stages = ", ".join(f"{k} {v:.1f}" for k, v in t1.items() if k != "total")
        acc90, compl = _points_quality(out / "points.ply", scene)
        print(f"| {scene.name} | {_iou(out, scene):.4f} | {f_err:+.3f} | {ch_h:.3f} ({100 * ch_h / diag:.2f} %) | "
              f"{ch_f:.3f} ({100 * ch_f / diag:.2f} %) | {ch_f / ch_h:.2f} | {chosen} | {acc90:.3f} | {compl:.1f} | "
              f"{sum(v for k, v in t1.items() if k != 'total'):.1f} | {fusion_s:.1f} | {stages} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
