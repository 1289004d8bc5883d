"""Peak memory and time of the hull carving against the grid resolution (issue 10, "Memory bounds").

``recon.carving.carve_hull`` on ``data/sample``'s true masks and cameras
(``masks/``, ``cameras_gt.json``; every 3rd frame: 12 views, 1280x960) in a
cylinder of radius 86 mm, once per resolution, each in its own subprocess:
its peak resident memory is that child's ``ru_maxrss`` (``os.wait4``), of
which the process before carving (interpreter, numpy, OpenCV, the masks)
is the ``base`` column. ``grid MB`` is the returned float32 grid,
``estimate MB`` what :func:`recon.carving.hull_peak_bytes` predicts for
the carve before it allocates.

    nice .venv/bin/python benchmarks/carving_memory.py [--resolutions 256 512 1024] [--tree DIR]

``--tree DIR`` runs another checkout's code (before/after a change; the
estimate column is then blank where that code has no estimate).

Measured 2026-12-01 (2 shared cores, loaded: seconds are upper bounds); the
same grids bit for bit before and after:

     res         grid  grid MB   peak MB before  peak MB after  estimate MB
     256  200x264x200       40              207            180          302
     512  400x528x400      322              799            492          619
    1024 800x1056x800     2578             5337           3297         3157 (now 3257)

``turntable reconstruct data/sample/images --frames 12 --no-fusion`` peaks at
9.9 GB at 1024 before and after (/usr/bin/time): that peak is in the hull mesh
stage (the grid, its copy and its padded copy in ``recon.meshing``), and the
hull's stage-cache checksum copies the grid once more (6.0 GB while saving).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample"


def _one(resolution: int) -> None:
    """Carve once in this process and print a JSON line."""
    import cv2
    import numpy as np

    from recon import carving
    from turntable.cameras_io import read_cameras

    seq = read_cameras(SAMPLE / "cameras_gt.json")
    idx = list(range(0, len(seq.frames), 3))
    masks = np.array([cv2.imread(str(SAMPLE / "masks" / Path(seq.frames[i].image).with_suffix(".png").name),
                                 cv2.IMREAD_GRAYSCALE) > 127 for i in idx])
    Ts = np.array([seq.frames[i].T_cam_table for i in idx])
    K = seq.intrinsics.K
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    estimate = None
    if hasattr(carving, "hull_peak_bytes"):
        estimate = carving.hull_peak_bytes(masks, K, Ts, radius_mm=86.0, resolution=resolution)
    t0 = time.perf_counter()
    hull = carving.carve_hull(masks, K, Ts, radius_mm=86.0, resolution=resolution)
    dt = time.perf_counter() - t0
    print(json.dumps({"seconds": dt, "base_bytes": base, "grid": list(hull.values.shape),
                      "grid_bytes": hull.values.nbytes, "estimate_bytes": estimate,
                      "inside": int(np.count_nonzero(hull.values > 0))}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout whose code runs (default: this one)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        _one(args.one)
        return 0
    print(f"carve_hull on {SAMPLE} (12 views), code: {args.tree}")
    print(f"{'res':>5} {'grid':>16} {'grid MB':>8} {'estimate MB':>11} {'peak MB':>8} {'base MB':>8} "
          f"{'seconds':>8} {'inside voxels':>13}")
    for r in args.resolutions:
        env = {**os.environ, "PYTHONPATH": str(args.tree.resolve())}
        proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--one", str(r)], cwd=args.tree,
                                env=env, stdout=subprocess.PIPE, text=True)
        out = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        if status != 0:
            print(f"{r:>5} failed (status {status})")
            continue
        d = json.loads(out.strip().splitlines()[-1])
        est = f"{d['estimate_bytes'] / 2**20:11.0f}" if d["estimate_bytes"] else f"{'-':>11}"
        print(f"{r:>5} {'x'.join(map(str, d['grid'])):>16} {d['grid_bytes'] / 2**20:8.0f} {est} "
              f"{usage.ru_maxrss / 1024:8.0f} {d['base_bytes'] / 2**20:8.0f} {d['seconds']:8.1f} {d['inside']:>13}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
