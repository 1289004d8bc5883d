"""Photo fidelity of the textured model against today's vertex-coloured one, on frames held out of texturing.

Every 4th frame is held out: ``turntable reconstruct --cameras --masks --no-fusion`` runs on the other
frames only (their images, masks and cameras), once per configuration:

* vertex colours, ``--no-texture --max-faces 100000`` (the model before issue 12),
* textured, ``--max-faces 50000 --lods 10000,2000`` (the default model and its two levels of detail,
  ``model_lod1.glb``/``model_lod2.glb``, which share its texture),
* textured, ``--max-faces 10000`` (a 10k model with its own atlas).

Each model is rendered into every held-out frame with ``recon.texture.render_albedo`` (ray cast,
unlit, as a glTF viewer samples the texture / interpolates ``COLOR_0``) and compared with the photo
inside the object's reference silhouette: PSNR (dB) and SSIM (``skimage.metrics``, Gaussian 1.5 px,
mean over the silhouette eroded by 2 px). Time: the ``texture`` stage of ``summary.json`` (atlas +
bake, all levels). Every GLB is checked with the Khronos validator (``benchmarks/gltf_validate.mjs``)
where node finds the npm package ``gltf-validator`` (set NODE_PATH), else the column says so.

Run: ``nice .venv/bin/python benchmarks/texture.py [--data data/sample /work/shared/realdata/squirrel ...]``
(each folder holds ``images/``, ``masks/`` and ``cameras_gt.json`` or ``cameras.json``). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh
from skimage.metrics import structural_similarity

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run without installing

from recon.texture import render_albedo  # noqa: E402
from recon.types import TableMesh  # noqa: E402
from turntable.cameras_io import read_cameras, write_cameras  # noqa: E402
from turntable.cli import main as turntable_main  # noqa: E402

HOLD_OUT_EVERY = 4
CONFIGS = [("vertex colours, 100k", ["--no-texture", "--max-faces", "100000"]),
           ("textured, 50k", ["--max-faces", "50000", "--lods", "10000,2000"]),
           ("textured, 10k", ["--max-faces", "10000"])]
REPO = Path(__file__).resolve().parents[1]


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


def load_model(out: Path, textured: bool, glb: str = "model.glb"):
    """(TableMesh mm, texcoords or None, texture or None) as a viewer loads model.glb / model.ply."""
    if not textured:
        m = trimesh.load(out / "model.ply", process=False)
        return TableMesh(np.asarray(m.vertices) * 1000.0, np.asarray(m.faces),
                         colors_rgb=np.asarray(m.visual.vertex_colors)[:, :3]), None, None
    m = trimesh.load(out / glb, force="mesh", process=False)
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


def khronos(glb: Path) -> str:
    """'0 errors, 0 warnings' (the validator's counts), or why it did not run."""
    node = shutil.which("node")
    if node is None:
        return "no node"
    res = subprocess.run([node, str(REPO / "benchmarks" / "gltf_validate.mjs"), str(glb)], capture_output=True,
                         text=True, timeout=300)
    try:
        report = json.loads(res.stdout.splitlines()[-1])
    except (IndexError, ValueError):
        return "validator not found (NODE_PATH)" if "gltf-validator" in res.stderr else f"exit {res.returncode}"
    return f"{report['errors']} errors, {report['warnings']} warnings"


def run(folder: Path) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="texbench") as tmp:
        work = Path(tmp)
        images, masks, cams, held = split_sequence(folder, work / "train")
        K = read_cameras(cams).intrinsics.K
        for label, flags in CONFIGS:
            out = work / label.replace(" ", "_").replace(",", "")
            code = turntable_main(["reconstruct", str(images), "--cameras", str(cams), "--masks", str(masks),
                                   "--no-fusion", "--quiet", "--out", str(out), *flags])
            if code not in (0, 3):
                raise SystemExit(f"{folder}: reconstruct {label} exited {code}")
            summary = json.loads((out / "summary.json").read_text())
            textured = "--no-texture" not in flags
            levels = [lv["file"] for lv in summary["texture"]["levels"]] if textured else ["model.ply"]
            for i, glb in enumerate(levels):
                model = load_model(out, textured, glb)
                p, s = fidelity(folder, held, K, model)
                side = model[2].shape[0] if textured else None
                rows.append({"data": folder.name, "model": label if i == 0 else f"{label}: {glb}",
                             "faces": len(model[0].faces), "texture": f"{side}²" if side else "-", "psnr": p,
                             "ssim": s, "time": summary["time_s"].get("texture") if i == 0 else None,
                             "colour_time": summary["time_s"].get("colour") if i == 0 else None,
                             "valid": khronos(out / glb) if textured else "-"})
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
    print("| data | model | faces | texture | held-out PSNR dB | SSIM | texture stage s | Khronos validator | note |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        t = "-" if r["time"] is None else f"{r['time']:.1f}"
        note = f"colour stage {r['colour_time']:.1f} s" if r["colour_time"] else ""
        print(f"| {r['data']} ({r['held_out']} held out) | {r['model']} | {r['faces']} | {r['texture']} | "
              f"{r['psnr']:.2f} | {r['ssim']:.4f} | {t} | {r['valid']} | {note} |")


if __name__ == "__main__":
    main()
