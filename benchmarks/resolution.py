"""Time and peak memory of ``turntable reconstruct`` against photo size (issue 9).

One rendered sequence (default ``data/sample``: 36 frames 1280x960, JPEG 92,
``cameras_gt.json``, ``object_gt.ply``) is upscaled to each size with
``cv2.resize(..., INTER_CUBIC)`` — as issue 9 made its 12 MP photos: no new
detail, larger pixels' worth of blur — and stored as JPEG quality 92 (the
1.2 MP entry is the original 1280x960 files, copied). Each size runs through
``turntable reconstruct`` with default options as its own subprocess; its peak
resident memory is that child's ``ru_maxrss`` (``os.wait4``).

Per size it prints: work size chosen, wall time and its ratio to the 1.2 MP
run, peak RSS, the focal-length error against the truth (the true f scales
with the image: ``f' = s f``), frames used (and frames lost at calibration),
and the model's symmetric mean Chamfer distance to ``object_gt.ply`` in % of
its bounding-box diagonal.

Bars (issue 9): 36 x 12 MP peak RSS <= 3 GB, wall <= 1.5x the 1280x960 run, no
frame lost, Chamfer no worse; 36 x 48 MP within 8 GB.

    nice .venv/bin/python benchmarks/resolution.py [--sizes 1.2 12] [--frames 36] [--work DIR] [--keep]

Measured 2026-12-01 on the 2-core machine shared with other sessions' jobs
(load 2.4-7 while it ran, so wall times are upper bounds and their ratios noisy),
``--sizes 1.2 3 12 --frames 36`` at 19:12 UTC and ``--sizes 1.2 48 --frames 36``
at 19:03 UTC (default options; work size chosen by the default policy):

       MP       size  work size  wall s x 1.2MP peak GB  f err %  used  lost Chamfer %
      1.2 1280x960   1280x960     165.3    1.00    1.98  +0.0200 36/36     0     0.336
        3 2000x1500  1317x987     205.7    1.24    1.98  +0.0652 36/36     0     0.343
       12 4032x3024  1317x987     222.8    1.35    1.98  +0.1128 36/36     0     0.339
      1.2 1280x960   1280x960     119.2    1.00    1.97  +0.0200 36/36     0     0.336
       48 8064x6048  1317x987     223.5    1.88    2.09  +0.1384 36/36     0     0.339

Issue 9 measured 36 x 12 MP at 623 s and 7.2 GB with a frame lost and 20
silhouettes rejected. The f error at 3-48 MP is the same before this work
(calibrate-sequence on the 36 x 12 MP frames: +0.1128 % with the code before
and after): edges of cubic-upscaled JPEGs, not the reduced copies.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: megapixels -> (width, height), 4:3 like the sample
SIZES = {1.2: (1280, 960), 3.0: (2000, 1500), 12.0: (4032, 3024), 48.0: (8064, 6048)}


def _size_of(mp: float) -> tuple[int, int]:
    if mp in SIZES:
        return SIZES[mp]
    w = int(round(np.sqrt(mp * 1e6 * 4 / 3) / 16) * 16)
    return w, w * 3 // 4


def make_inputs(sample: Path, dest: Path, size: tuple[int, int], frames: int) -> list[str]:
    """The first of every ``36 / frames`` frames of ``sample``, at ``size`` (JPEG 92); their names."""
    files = sorted((sample / "images").iterdir())
    pick = [files[i * len(files) // frames] for i in range(min(frames, len(files)))]
    dest.mkdir(parents=True, exist_ok=True)
    for f in pick:
        img = cv2.imread(str(f))
        if img.shape[1::-1] == size:
            shutil.copy(f, dest / f.name)
        else:
            big = cv2.resize(img, size, interpolation=cv2.INTER_CUBIC)
            cv2.imwrite(str(dest / f.name), big, [cv2.IMWRITE_JPEG_QUALITY, 92])
    return [f.name for f in pick]


def run_reconstruct(images: Path, out: Path, extra: list[str]) -> tuple[float, float, int, str]:
    """(wall s, peak RSS GB, exit code, stderr tail) of one ``turntable reconstruct`` subprocess."""
    cmd = [sys.executable, "-m", "turntable", "reconstruct", str(images), "--r-outer", "80", "--r-inner", "50",
           "--out", str(out), "--overwrite", "--quiet", *extra]
    log = out.parent / "reconstruct.log"
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
        _, status, ru = os.wait4(p.pid, 0)  # this child's own rusage (not the sum of all children)
    wall = time.perf_counter() - t0
    p.returncode = rc = os.waitstatus_to_exitcode(status)
    return wall, ru.ru_maxrss / 1024 ** 2, rc, log.read_text()[-600:]


def chamfer_pct(model: Path, gt_ply: Path) -> float:
    """Symmetric mean distance between ``model`` (a mesh file in metres) and ``gt_ply`` (mm), in % of the truth's
    bounding-box diagonal (30 000 surface samples each)."""
    import trimesh
    from scipy.spatial import cKDTree

    m = trimesh.load(model, force="mesh", skip_materials=True)
    gt = trimesh.load(gt_ply)
    a, b = m.sample(30000, seed=0) * 1000.0, gt.sample(30000, seed=0)
    ch = 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())
    return 100.0 * float(ch) / float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sample", default=str(ROOT / "data" / "sample"))
    ap.add_argument("--sizes", nargs="+", type=float, default=[1.2, 3.0, 12.0, 48.0], metavar="MP")
    ap.add_argument("--frames", type=int, default=36, metavar="N", help="frames spread evenly over the sample")
    ap.add_argument("--work", metavar="DIR", help="where the upscaled photos and outputs go (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep DIR afterwards")
    ap.add_argument("--extra", default="", help="more reconstruct options, one string (e.g. '--work-size full')")
    args = ap.parse_args(argv)
    sample = Path(args.sample)
    gt = json.loads((sample / "cameras_gt.json").read_text())
    f_true = float(np.asarray(gt["intrinsics"]["K"], float)[0, 0])
    W0 = int(gt["intrinsics"]["width"])
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="resolution_"))
    load = os.getloadavg()
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores, "
          f"load {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {sample.name}, {args.frames} frames; "
          f"upscaled with cv2.resize INTER_CUBIC, JPEG 92")
    head = (f"{'MP':>5} {'size':>10} {'work size':>10} {'wall s':>7} {'x 1.2MP':>7} {'peak GB':>7} "
            f"{'f err %':>8} {'used':>5} {'lost':>5} {'Chamfer %':>9}")
    print(head)
    base_wall = None
    try:
        for mp in args.sizes:
            size = _size_of(mp)
            images = work / f"{mp:g}MP" / "images"
            names = make_inputs(sample, images, size, args.frames)
            out = work / f"{mp:g}MP" / "out"
            wall, rss, rc, tail = run_reconstruct(images, out, args.extra.split())
            if rc not in (0, 3):
                print(f"{mp:5g} {size[0]}x{size[1]}: reconstruct failed (exit {rc}): {tail}")
                continue
            s = json.loads((out / "summary.json").read_text())
            f_err = 100.0 * (s["focal_px"] / (f_true * size[0] / W0) - 1.0)
            lost = [n for n, why in s["frames_skipped"].items() if not why.startswith("silhouette")]
            ws = s.get("work_size") or {}
            if mp == 1.2 or base_wall is None:
                base_wall = base_wall or wall
            ratio = wall / base_wall
            print(f"{mp:5g} {size[0]:>4}x{size[1]:<5} {ws.get('width', 0):>4}x{ws.get('height', 0):<5} "
                  f"{wall:7.1f} {ratio:7.2f} {rss:7.2f} {f_err:+8.4f} {s['frames_used']:>2}/{len(names):<2} "
                  f"{len(lost):>5} {chamfer_pct(out / 'model.glb', sample / 'object_gt.ply'):9.3f}", flush=True)
            if lost:
                why = "; ".join(f"{n}: {s['frames_skipped'][n]}" for n in lost)
                print(f"      lost: {why}")
            shutil.rmtree(images)  # the photos are the large part; keep the outputs while DIR is kept
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
