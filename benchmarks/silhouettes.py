"""Automatic silhouettes (recon.silhouettes) against the synthetic renderer's ground truth.

For each sequence folder written by ``turntable synth`` (images/, masks/,
cameras_gt.json) runs :func:`recon.silhouettes.estimate_silhouettes` with the
ground-truth cameras and prints per sequence: mean / min IoU, frames kept
conservatively and rejected, the IoU of every rejected frame (the bar: none
rejected with IoU >= 0.95), the largest share of the true silhouette that
``mask | unknown`` misses in a kept frame (what carving could eat: 0 is fail
safe), and seconds per frame. Without arguments it renders the 3 backdrops x
2 objects (36 frames, 1280x960) into a temporary folder first (slow: ~2 min
per sequence on 2 cores).

Run: ``nice .venv/bin/python benchmarks/silhouettes.py [SEQ_DIR ...]``
"""

from __future__ import annotations

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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calib.target import TargetSpec  # noqa: E402
from recon.silhouettes import estimate_silhouettes  # noqa: E402
from turntable.cameras_io import read_cameras  # noqa: E402


def load_sequence(folder: Path):
    seq = read_cameras(folder / "cameras_gt.json")
    imgs, gts = [], []
    for f in seq.frames:
        img = cv2.imread(str(folder / f.image), cv2.IMREAD_COLOR)
        imgs.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        gts.append(cv2.imread(str(folder / "masks" / (Path(f.image).stem + ".png")), cv2.IMREAD_GRAYSCALE) > 127)
    T = np.stack([f.T_cam_table for f in seq.frames])
    meta = json.loads((folder / "scene.json").read_text()) if (folder / "scene.json").exists() else {}
    opts = meta.get("options", meta)
    spec = TargetSpec(float(opts.get("r_outer", 80.0)), float(opts.get("r_inner", 50.0)),
                      float(opts.get("stroke", 3.0)))
    return np.stack(imgs), np.stack(gts), seq.intrinsics.K, T, spec


def render_default(root: Path) -> list[Path]:
    from turntable.synth import SynthOptions, make_sequence

    out = []
    for obj in ("vase", "chair"):
        for backdrop in ("dark", "light", "clutter"):
            d = root / f"{obj}_{backdrop}"
            make_sequence(d, SynthOptions(object=obj, backdrop=backdrop, seed=11))
            out.append(d)
    return out


def main(argv: list[str]) -> None:
    folders = [Path(a) for a in argv]
    tmp = None
    if not folders:
        tmp = tempfile.TemporaryDirectory()
        folders = render_default(Path(tmp.name))
    rows = []
    for folder in folders:
        imgs, gts, K, T, spec = load_sequence(folder)
        t0 = time.perf_counter()
        res = estimate_silhouettes(imgs, K, T, spec)
        dt = (time.perf_counter() - t0) / len(imgs)
        ious = np.array([(m & g).sum() / max((m | g).sum(), 1) for m, g in zip(res.masks, gts, strict=True)])
        rejected = [i for i, s in enumerate(res.status) if s.startswith("rejected")]
        conservative = sum(s.startswith("conservative") for s in res.status)
        kept = [i for i in range(len(imgs)) if i not in rejected]
        missed = max((float((g & ~(m | u)).sum() / max(g.sum(), 1)) for m, u, g in
                      zip(res.masks[kept], res.unknown[kept], gts[kept], strict=True)), default=0.0)
        dropped = ", ".join(f"{i}: {ious[i]:.3f}" for i in rejected) or "-"
        rows.append((folder.name, len(imgs), imgs.shape[2], imgs.shape[1], ious.mean(), ious.min(), conservative,
                     len(rejected), dropped, missed, dt))
    print(f"## Automatic silhouettes — {datetime.date.today()}, {platform.platform()}, {os.cpu_count()} CPUs\n")
    print("| sequence | frames | size | mean IoU | min IoU | conservative | rejected | rejected frames: IoU "
          "| max missed by mask+unknown | s / frame |")
    print("|---|---:|---|---:|---:|---:|---:|---|---:|---:|")
    for name, n, w, h, mean, lo, cons, rej, dropped, missed, dt in rows:
        print(f"| {name} | {n} | {w}x{h} | {mean:.4f} | {lo:.4f} | {cons} | {rej} | {dropped} | {missed:.4f} "
              f"| {dt:.2f} |")
    print(f"| **all** | {sum(r[1] for r in rows)} | | **{np.mean([r[4] for r in rows]):.4f}** | "
          f"{min(r[5] for r in rows):.4f} | {sum(r[6] for r in rows)} | {sum(r[7] for r in rows)} | | "
          f"{max(r[9] for r in rows):.4f} | {np.mean([r[10] for r in rows]):.2f} |")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main(sys.argv[1:])
