"""Real photographs with published cameras: the user's command end to end, judged against reference silhouettes.

Runs every sequence in ``../shared/realdata`` (each folder: ``images/``,
``masks/``, ``cameras.json``; see its README) through ``turntable reconstruct``
as a user would, in a subprocess (real exit codes, wall time, peak memory):

* ``hull``:  ``--cameras --masks --no-fusion`` (the visual hull alone);
* ``fused``: ``--cameras --masks`` (the default model, fusion on), in the same
  OUT so that cameras, silhouettes and hull are reused;
* ``auto``:  ``--cameras`` only (automatic silhouettes), for the sequences
  named by ``--auto``.

No target radii are given: these photos have no ring target, so the working
volume must come from the cameras and silhouettes. Per run it prints: exit
code, connected pieces and the largest piece's share of the faces, whether
the mesh is watertight, mean and min IoU of the model projected into every
frame against the reference masks, the fused/hull surface-area and volume
ratios, frames rejected, wall time and peak resident memory. ``--look DIR``
also writes, per run, the model's outline over two photos and the model
shaded from four sides, to be looked at.

Bars (issue 8): ``--cameras --masks``: one watertight piece (largest >= 99.9 %
of faces), mean IoU >= 0.96, fused/hull area <= 1.10, volume >= 0.85;
squirrel with automatic silhouettes: completes, <= 1 frame rejected, mean
IoU >= 0.96.

    .venv/bin/python benchmarks/real.py [--data ../shared/realdata] [--only temple] [--look /tmp/look]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _turntable() -> list[str]:
    exe = Path(sys.executable).with_name("turntable")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "turntable"]


def _run(args: list[str]) -> tuple[int, float, float, str]:
    """(exit code, wall s, peak RSS GB of this child, stderr tail)."""
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    p = subprocess.run(_turntable() + ["reconstruct", *args], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    # ru_maxrss of children is the max over all waited-for children: exact when it grew, a bound otherwise
    peak = max(after, before) / 1024 ** 2
    return p.returncode, wall, peak, (p.stderr.strip().splitlines() or [""])[-1]


def _load_mesh(path: Path):
    import trimesh

    m = trimesh.load(path, force="mesh", process=False)
    m.vertices = np.asarray(m.vertices) * 1000.0  # exports are in metres; cameras in mm
    return m


def _projected(mesh, K, T, size) -> np.ndarray:
    """(H, W) bool: the pixels whose centre ray hits the mesh (ray casting)."""
    import open3d as o3d

    from recon.stereo import pixel_rays_table

    W, H = size
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    centre, dirs = pixel_rays_table(K, T, size)
    rays = np.concatenate([np.broadcast_to(centre, dirs.shape), dirs], -1).astype(np.float32)
    hit = np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    return hit.reshape(H, W)


def _ious(mesh, seq, data: Path) -> list[float]:
    from turntable.images import IMAGE_SUFFIXES

    masks = {p.stem: p for p in (data / "masks").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    K = seq.intrinsics.K
    size = (seq.intrinsics.width, seq.intrinsics.height)
    out = []
    for f in seq.frames:
        p = masks.get(Path(f.image).stem)
        if p is None:
            continue
        ref = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127
        got = _projected(mesh, K, np.asarray(f.T_cam_table), size)
        out.append(float((ref & got).sum() / max((ref | got).sum(), 1)))
    return out


def _look(mesh, seq, data: Path, folder: Path, tag: str) -> None:
    """The model's outline over two photos, and the model shaded from four sides."""
    import open3d as o3d

    from calib.camera import look_at

    folder.mkdir(parents=True, exist_ok=True)
    K = seq.intrinsics.K
    size = (seq.intrinsics.width, seq.intrinsics.height)
    frames = [seq.frames[0], seq.frames[len(seq.frames) // 3]]
    tiles = []
    for f in frames:
        img = cv2.imread(str(data / "images" / Path(f.image).name))
        m = _projected(mesh, K, np.asarray(f.T_cam_table), size).astype(np.uint8)
        cnts, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, cnts, -1, (0, 255, 0), 1)
        tiles.append(img)
    cv2.imwrite(str(folder / f"{tag}_overlay.png"), np.hstack(tiles))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    lo, hi = mesh.bounds
    c = 0.5 * (lo + hi)
    r = float(np.linalg.norm(hi - lo))
    n = 480
    Kr = np.array([[1.1 * n, 0, (n - 1) / 2], [0, 1.1 * n, (n - 1) / 2], [0, 0, 1.0]])
    views = []
    for az in (0, 90, 180, 270):
        a = np.radians(az)
        eye = c + r * np.array([np.cos(a), 0.5, np.sin(a)])
        T = look_at(eye, c)
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(Kr), o3d.core.Tensor(T), n, n)
        hit = scene.cast_rays(rays)
        nrm = hit["primitive_normals"].numpy()
        d = rays.numpy()[..., 3:]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        shade = np.abs((nrm * d).sum(-1))
        img = np.where(np.isfinite(hit["t_hit"].numpy()), 40 + 215 * shade, 0).astype(np.uint8)
        views.append(img)
    cv2.imwrite(str(folder / f"{tag}_views.png"), np.hstack(views))


def _stats(model: Path) -> dict:
    import trimesh

    m = trimesh.load(model, force="mesh", process=False)
    parts = m.split(only_watertight=False)
    largest = max((len(p.faces) for p in parts), default=0)
    m1 = trimesh.Trimesh(np.asarray(m.vertices) * 1000.0, m.faces, process=True)
    return {"pieces": len(parts), "largest": largest / max(len(m.faces), 1), "watertight": bool(m1.is_watertight),
            "area": float(m1.area), "volume": float(m1.volume)}


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    p.add_argument("--only", nargs="+", help="sequence names (default: every folder with cameras.json)")
    p.add_argument("--auto", nargs="*", default=["squirrel"], help="also run these without --masks")
    p.add_argument("--out", default="/tmp/turntable_bench_real")
    p.add_argument("--look", metavar="DIR", help="write overlays and renders here")
    p.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more reconstruct options")
    a = p.parse_args(argv)
    data = Path(a.data)
    if not data.is_dir():
        print(f"benchmarks/real.py: {data} is absent (the real sequences live in ../shared/realdata); nothing to run")
        return 0
    from turntable.cameras_io import read_cameras

    seqs = sorted(d for d in data.iterdir() if (d / "cameras.json").is_file() and (not a.only or d.name in a.only))
    print(f"## Real sequences — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
          f"{platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}\n")
    print("`turntable reconstruct IMAGES --cameras cameras.json [--masks masks] [--no-fusion]`, default options, "
          "no target radii.\n")
    print("| sequence | run | exit | pieces | largest % | watertight | IoU mean | IoU min | area/hull | "
          "volume/hull | rejected | wall s | peak GB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for d in seqs:
        seq = read_cameras(d / "cameras.json")
        out_root = Path(a.out) / d.name
        shutil.rmtree(out_root, ignore_errors=True)
        base = [str(d / "images"), "--cameras", str(d / "cameras.json"), "--quiet", *a.extra]
        runs = [("hull", "masked", ["--masks", str(d / "masks"), "--no-fusion"]),
                ("fused", "masked", ["--masks", str(d / "masks")])]
        if d.name in (a.auto or []):
            runs.append(("auto", "auto", []))
        hull = None
        for tag, folder, extra in runs:
            out = out_root / folder
            code, wall, peak, err = _run(base + ["--out", str(out)] + extra)
            model = out / "model.ply"
            if code not in (0, 1) and not (out / "summary.json").is_file():
                print(f"| {d.name} | {tag} | {code} | — | — | — | — | — | — | — | — | {wall:.0f} | {peak:.1f} |"
                      f"  {err[:160]}", flush=True)
                continue
            s = _stats(model)
            if tag == "hull":
                hull = s
                shutil.copy(model, out / "model_hull.ply")
            summary = json.loads((out / "summary.json").read_text())
            mesh = _load_mesh(model)
            ious = _ious(mesh, seq, d)
            ratio = (f"{s['area'] / hull['area']:.2f} | {s['volume'] / hull['volume']:.2f}"
                     if hull is not None and tag != "hull" else "— | —")
            print(f"| {d.name} | {tag} | {code} | {s['pieces']} | {100 * s['largest']:.2f} | "
                  f"{'yes' if s['watertight'] else 'NO'} | {np.mean(ious):.4f} | {np.min(ious):.4f} | {ratio} | "
                  f"{len(summary.get('frames_skipped', {}))} | {wall:.0f} | {peak:.1f} |", flush=True)
            if a.look:
                _look(mesh, seq, d, Path(a.look), f"{d.name}_{tag}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
