"""Photo fidelity of the textured model against today's vertex-coloured one, on frames held out of texturing.

Every 4th frame is held out: ``turntable reconstruct --cameras --masks --no-fusion`` runs on the other
frames only (their images, masks and cameras), once per configuration:

* vertex colours, ``--no-texture --max-faces 100000`` (the model before issue 12),
* textured, ``--max-faces 50000`` (the new default; texture side chosen by ``recon.texture.texture_side``),
* textured, ``--max-faces 10000``,

and, on the 50 000-face mesh, the texture baked at a fixed 2048² (``uv_atlas`` + ``bake_texture``).
Each model is rendered into every held-out frame with ``recon.texture.render_albedo`` (ray cast,
unlit, as a glTF viewer samples the texture / interpolates ``COLOR_0``) and compared with the photo
inside the object's reference silhouette: PSNR (dB) and SSIM (``skimage.metrics``, Gaussian 1.5 px,
mean over the silhouette eroded by 2 px). Times: the ``texture`` stage of ``summary.json`` (atlas +
bake) for the runs, and atlas and bake apart for the fixed 2048².

Run: ``nice .venv/bin/python benchmarks/texture.py [--data data/sample /work/shared/realdata/squirrel ...]``
(each folder holds ``images/``, ``masks/`` and ``cameras_gt.json`` or ``cameras.json``). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh
from skimage.metrics import structural_similarity

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run without installing

from recon.texture import bake_texture, render_albedo, uv_atlas  # noqa: E402
from recon.types import TableMesh  # noqa: E402
from turntable.cameras_io import read_cameras, write_cameras  # noqa: E402
from turntable.cli import main as turntable_main  # noqa: E402

HOLD_OUT_EVERY = 4
CONFIGS = [("vertex colours, 100k", ["--no-texture", "--max-faces", "100000"]),
           ("textured, 50k", ["--max-faces", "50000"]),
           ("textured, 10k", ["--max-faces", "10000"])]


def _cameras_file(folder: Path) -> Path:
    for name in ("cameras_gt.json", "cameras.json"):
        if (folder / name).is_file():
            return folder / name
    raise SystemExit(f"{folder}: no cameras_gt.json or cameras.json")


def _mask_path(folder: Path, image: str) -> Path:
    stem = Path(image).stem
    for p in (folder / "masks").glob(stem + ".*"):
        return p
    raise SystemExit(f"{folder}: no mask for {image}")


def split_sequence(folder: Path, work: Path) -> tuple[Path, Path, Path, list]:
    """Training images/masks (symlinks) and cameras in ``work``; the held-out frames' poses."""
    seq = read_cameras(_cameras_file(folder))
    if seq.intrinsics.dist is not None and np.any(seq.intrinsics.dist):
        raise SystemExit(f"{folder}: distorted photos; this benchmark compares undistorted ones")
    frames = [f for f in seq.frames if f.ok]
    held = [f for i, f in enumerate(frames) if i % HOLD_OUT_EVERY == HOLD_OUT_EVERY - 1]
    train = [f for f in frames if f not in held]
    (work / "images").mkdir(parents=True)
    (work / "masks").mkdir()
    for f in train:
        name = Path(f.image).name
        (work / "images" / name).symlink_to((folder / "images" / name).resolve())
        m = _mask_path(folder, name)
        (work / "masks" / m.name).symlink_to(m.resolve())
    cams = work / "cameras.json"
    write_cameras(cams, dataclasses.replace(seq, frames=tuple(train)))
    return work / "images", work / "masks", cams, held


def load_model(out: Path, textured: bool):
    """(TableMesh mm, texcoords or None, texture or None) as a viewer loads model.glb / model.ply."""
    if not textured:
        m = trimesh.load(out / "model.ply", process=False)
        return TableMesh(np.asarray(m.vertices) * 1000.0, np.asarray(m.faces),
                         colors_rgb=np.asarray(m.visual.vertex_colors)[:, :3]), None, None
    m = trimesh.load(out / "model.glb", force="mesh", process=False)
    uv = np.asarray(m.visual.uv, np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # trimesh's OBJ convention back to glTF's
    tex = np.asarray(m.visual.material.baseColorTexture.convert("RGB"))
    return TableMesh(np.asarray(m.vertices) * 1000.0, np.asarray(m.faces)), uv, tex


def fidelity(folder: Path, held, seq_K, model) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over the held-out frames, inside the reference silhouette."""
    mesh, uv, tex = model
    psnr, ssim = [], []
    for f in held:
        name = Path(f.image).name
        photo = cv2.cvtColor(cv2.imread(str(folder / "images" / name)), cv2.COLOR_BGR2RGB)
        mask = cv2.imread(str(_mask_path(folder, name)), cv2.IMREAD_GRAYSCALE) > 0
        H, W = photo.shape[:2]
        img, hit = render_albedo(mesh, seq_K, f.T_cam_table, (W, H), texcoords=uv, texture_rgb=tex)
        inside = mask & hit
        err = (img[inside].astype(np.float64) - photo[inside].astype(np.float64)) ** 2
        psnr.append(10.0 * np.log10(255.0**2 / max(err.mean(), 1e-12)))
        _, smap = structural_similarity(photo, img, data_range=255, channel_axis=2, gaussian_weights=True,
                                        sigma=1.5, use_sample_covariance=False, full=True)
        core = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        ssim.append(float(smap.mean(axis=2)[core].mean()))
    return float(np.mean(psnr)), float(np.mean(ssim))


def fixed_2048(folder: Path, work: Path, out50: Path, K):
    """The 50k mesh's texture baked at 2048² from the training frames: (model, atlas s, bake s)."""
    ply = trimesh.load(out50 / "model.ply", process=False)
    V = np.asarray(ply.vertices) * 1000.0
    F = np.asarray(ply.faces)
    seq = read_cameras(work / "cameras.json")
    images = [cv2.cvtColor(cv2.imread(str(work / "images" / Path(f.image).name)), cv2.COLOR_BGR2RGB)
              for f in seq.frames]
    masks = [cv2.imread(str(_mask_path(folder, Path(f.image).name)), cv2.IMREAD_GRAYSCALE) for f in seq.frames]
    Ts = np.stack([f.T_cam_table for f in seq.frames])
    t0 = time.perf_counter()
    src, faces, uv = uv_atlas(V, F, 2048)
    t1 = time.perf_counter()
    mesh = TableMesh(V[src], faces, np.asarray(ply.vertex_normals)[src], np.asarray(ply.visual.vertex_colors)[src, :3])
    tex = bake_texture(mesh, uv, images, K, Ts, masks=masks, size=2048)
    t2 = time.perf_counter()
    return (mesh, uv, tex), t1 - t0, t2 - t1, len(images), images[0].shape


def run(folder: Path) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="texbench") as tmp:
        work = Path(tmp)
        images, masks, cams, held = split_sequence(folder, work / "train")
        K = read_cameras(cams).intrinsics.K
        outs = {}
        for label, flags in CONFIGS:
            out = work / label.replace(" ", "_").replace(",", "")
            code = turntable_main(["reconstruct", str(images), "--cameras", str(cams), "--masks", str(masks),
                                   "--no-fusion", "--quiet", "--out", str(out), *flags])
            if code not in (0, 3):
                raise SystemExit(f"{folder}: reconstruct {label} exited {code}")
            summary = json.loads((out / "summary.json").read_text())
            textured = "--no-texture" not in flags
            model = load_model(out, textured)
            p, s = fidelity(folder, held, K, model)
            side = model[2].shape[0] if textured else None
            rows.append({"data": folder.name, "model": label, "faces": summary["mesh"]["faces"],
                         "texture": f"{side}²" if side else "-", "psnr": p, "ssim": s,
                         "time": summary["time_s"].get("texture"), "colour_time": summary["time_s"].get("colour")})
            outs[label] = out
        model, t_atlas, t_bake, n_views, shape = fixed_2048(folder, work / "train", outs["textured, 50k"], K)
        p, s = fidelity(folder, held, K, model)
        rows.append({"data": folder.name, "model": "textured, 50k, fixed 2048²", "faces": len(model[0].faces),
                     "texture": "2048²", "psnr": p, "ssim": s, "time": t_atlas + t_bake,
                     "note": f"atlas {t_atlas:.1f} s + bake {t_bake:.1f} s, {n_views} views {shape[1]}x{shape[0]}",
                     "colour_time": None})
    for r in rows:
        r["held_out"] = len(held)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", default=["data/sample"], help="sequence folders")
    args = ap.parse_args()
    rows = []
    for d in args.data:
        rows += run(Path(d))
        print(f"done {d}", file=sys.stderr, flush=True)
    print(f"\n{platform.node()} {os.cpu_count()} cores, {time.strftime('%Y-%m-%d %H:%M')}\n")
    print("| data | model | faces | texture | held-out PSNR dB | SSIM | texture stage s | note |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        t = "-" if r["time"] is None else f"{r['time']:.1f}"
        note = r.get("note") or (f"colour stage {r['colour_time']:.1f} s" if r["colour_time"] else "")
        print(f"| {r['data']} ({r['held_out']} held out) | {r['model']} | {r['faces']} | {r['texture']} | "
              f"{r['psnr']:.2f} | {r['ssim']:.4f} | {t} | {note} |")


if __name__ == "__main__":
    main()
