"""Time and peak memory of ``turntable calibrate-sequence`` against the number of frames (issue 10).

One rendered turntable sequence (``turntable synth``) is calibrated with
``--frames N`` (N frames spread evenly over it) for each N, each run its own
``python -m turntable`` subprocess; its peak resident memory is that child's
``ru_maxrss`` (``os.wait4``). Per N it prints the wall time, the part of it
after the per-frame stage (the joint fit: the time after the progress line
``2N/2N``, i.e. the fit, the marks read again and writing cameras.json),
the peak memory, seconds per frame for both, and the focal length found.

Cost should be linear in N: seconds per frame about constant down the table
(on a loaded machine the wall times are noisy: ``--kernels`` times the joint
fit's residuals and Jacobian per row on synthetic problems instead).
``--tree DIR`` runs another checkout's code (e.g. ``git archive HEAD | tar -x
-C DIR``) to compare before and after a change.

    .venv/bin/turntable synth /tmp/seq500 --frames 500 --size 640x480 --focal-px 750 --step-deg 0.72 --seed 1
    nice .venv/bin/python benchmarks/sequence_scaling.py /tmp/seq500/images [--frames 60 120 250 500] [--tree DIR]
    nice .venv/bin/python benchmarks/sequence_scaling.py --kernels [--frames 60 120 250 500]

Measured 2026-12-01 on the 2-core machine shared with other sessions (load 2.5-8.5,
so wall times are upper bounds), ``/tmp/seq500``: 500 frames 640x480, f 750,
step 0.72 deg, seed 1. "fit" = after the per-frame stage: the joint fit and
the marks read a second time (about half of it at 250 frames).

    code before b1664a1 (dense Jacobian and solve)   after (blocked, Schur complement)
    frames  wall s  fit s  fit s/frame  peak MB      wall s  fit s  fit s/frame  peak MB  f px
        60    42.4   25.5       0.424      167        43.5   11.7       0.196      157   749.110
       120    68.7   44.3       0.369      291        50.8   20.1       0.168      220   749.148
       250   188.2  129.0       0.516      716       176.8  100.6       0.403      365   749.133
       500  1145.7  990.6       1.981     2115       476.5  175.4       0.351      644   749.138

``--kernels`` (Jacobian per row, best of 5): 28.4 / 28.9 / 32.6 us before, 13.6 /
9.3 / 9.9 us after at 60 / 250 / 500 frames. The super-linear part before was the
covariance's non-BLAS ``einsum`` of the dense (rows, n_params) Jacobian with
itself (rows x n_params^2 per fit stage) and the dense arrays themselves.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_once(images: Path, n: int, tree: Path, timeout_s: float) -> dict:
    """One calibrate-sequence subprocess: wall s, per-frame stage s, peak MB, focal px (None on failure)."""
    with tempfile.TemporaryDirectory() as tmp:
        out, log = Path(tmp) / "cameras.json", Path(tmp) / "stderr.txt"
        cmd = [sys.executable, "-m", "turntable", "calibrate-sequence", str(images), "--r-outer", "80",
               "--r-inner", "50", "--stroke", "3", "--frames", str(n), "--out", str(out)]
        env = {**os.environ, "PYTHONPATH": str(tree)}
        t0 = time.perf_counter()
        with open(log, "w") as err:
            proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.DEVNULL, stderr=err)
            timed_out = False
            while True:  # os.wait4 reaps the child and gives its own peak memory
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if time.perf_counter() - t0 > timeout_s:
                    proc.kill()
                    timed_out = True
                    _, status, usage = os.wait4(proc.pid, 0)
                    break
                time.sleep(0.1)
        wall = time.perf_counter() - t0
        text = log.read_text()
        # the per-frame stage's end: "frames done in X s" (older code: the progress line "2N/2N (X s)")
        per_frame = [float(m.group(1)) for m in re.finditer(rf"(?:frames done in\s+|{2 * n}/{2 * n} \()([\d.]+) s",
                                                             text)]
        focal = json.loads(out.read_text())["intrinsics"]["K"][0][0] if out.exists() else None
        return {"frames": n, "wall_s": wall, "per_frame_stage_s": per_frame[-1] if per_frame else float("nan"),
                "peak_mb": usage.ru_maxrss / 1024, "focal_px": focal, "timed_out": timed_out}


def kernels(frame_counts, points_per_edge: int = 100) -> None:
    """Time per row of the joint fit's residuals and Jacobian on synthetic turntable problems (no images).

    Four exact edge circles per frame (``points_per_edge`` points each, as
    ``POINT_BUDGET`` gives from 50 frames on) seen by a camera 450 mm away;
    best of 5. Flat ns/row down the table: linear cost, whatever the load.
    """
    import numpy as np

    from calib.camera import circle_points_table, look_at, make_T, project_points
    from calib.sequence_model import FitState, FrameEdges, JointProblem, rot_y
    from calib.types import EdgePoints, TargetObservation

    K = np.array([[750.0, 0.0, 319.5], [0.0, 750.0, 239.5], [0.0, 0.0, 1.0]])
    T_ca = look_at(np.array([0.0, 225.0, -390.0]), np.zeros(3))
    print(f"{'frames':>6} {'rows':>7} {'residuals ms':>12} {'ns/row':>7} {'Jacobian ms':>12} {'ns/row':>7}")
    for n in frame_counts:
        theta = np.radians(np.arange(n) * 360.0 / n)
        frames = []
        for th in theta:
            T = T_ca @ make_T(rot_y(th), np.zeros(3))
            edges = tuple(EdgePoints(project_points(K, T, circle_points_table(r + s * 1.5, points_per_edge)), r, s)
                          for r in (80.0, 50.0) for s in (-1, 1))
            frames.append(FrameEdges.from_observation(TargetObservation(edges, 640, 480), points_per_edge))
        st = FitState(K=K, dist=np.zeros(5), stroke=3.0, R_cam_axis=T_ca[:3, :3], t_cam_axis=T_ca[:3, 3],
                      d_xz=np.zeros(2), theta=theta)
        p = JointProblem(frames, st, ("f", "k1"), True, "turntable", free_theta=np.arange(n) > 0,
                         mark_R=[T_ca[:3, :3] @ rot_y(th) for th in theta], mark_w=np.full(n, 50.0))
        x = np.zeros(p.n_params)
        t_res = t_jac = float("inf")
        for _ in range(5):
            t0 = time.perf_counter()
            p.residuals(x)
            t1 = time.perf_counter()
            p.jacobian(x)
            t_res, t_jac = min(t_res, t1 - t0), min(t_jac, time.perf_counter() - t1)
        print(f"{n:>6} {p.n_rows:>7} {1e3 * t_res:12.1f} {1e9 * t_res / p.n_rows:7.0f} {1e3 * t_jac:12.1f} "
              f"{1e9 * t_jac / p.n_rows:7.0f}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path, nargs="?", help="folder of a rendered turntable sequence")
    ap.add_argument("--frames", type=int, nargs="+", default=[60, 120, 250, 500])
    ap.add_argument("--tree", type=Path, default=ROOT, help="checkout whose code runs (default: this one)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run before it is stopped")
    ap.add_argument("--kernels", action="store_true",
                    help="only time the joint fit's residuals and Jacobian per row on synthetic problems")
    args = ap.parse_args(argv)
    if args.kernels:
        sys.path.insert(0, str(args.tree.resolve()))
        kernels(args.frames)
        return 0
    if args.images is None:
        ap.error("the images folder is needed (or --kernels)")
    print(f"calibrate-sequence on {args.images} (code: {args.tree})")
    print(f"{'frames':>6} {'wall s':>8} {'s/frame':>8} {'frames s':>9} {'fit s':>8} {'fit s/frame':>11} "
          f"{'peak MB':>8} {'f px':>9}")
    for n in args.frames:
        r = run_once(args.images.resolve(), n, args.tree.resolve(), args.timeout)
        fit = r["wall_s"] - r["per_frame_stage_s"]
        if r["focal_px"] is not None:
            focal = f"{r['focal_px']:9.3f}"
        else:
            focal = "  timeout" if r["timed_out"] else "   failed"
        print(f"{n:>6} {r['wall_s']:8.1f} {r['wall_s'] / n:8.3f} {r['per_frame_stage_s']:9.1f} {fit:8.1f} "
              f"{fit / n:11.4f} {r['peak_mb']:8.0f} {focal}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
