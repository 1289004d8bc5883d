"""Noise study of the single-view solvers: the paper's §5.1 set-up, plus OpenCV.

f = 3000 px; normal (-0.07, 0.93, 0.34) (normalised, flipped towards the
camera); T = (-4.3, 41, 750) mm; R1 = 50, R2 = 28 mm; 1280x960, principal
point at the image centre. Centre-line points (side 0) evenly spaced on each
circle with Gaussian noise sigma (pixels, both coordinates). For each sigma and
trial (seeded) the three solvers run as ``calib.calibrate.calibrate_view`` runs
them (``refine`` starts from ``pencil``);
beside them ``cv2.calibrateCamera`` on ONE view of a 9x9-inner-corner
chessboard of the same extent (100 mm square, 12.5 mm pitch) at the same pose
with the same noise on the corners (principal point fixed, aspect fixed, no
distortion, initial focal 1.25 x true).

Prints markdown tables: median relative error of f (%), median angle error of
the normal (deg), median relative error of T (%), refine's median reported
1-sigma of f (%), and timings. ``--tilt-study`` adds f accuracy against the
tilt of the table from the optical axis (the basis of ``MIN_TILT_DEG``).

    nice .venv/bin/python benchmarks/calib_noise.py [--trials 1000] [--points 360]   (about a minute on an idle machine)
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.calibrate import SOLVERS, calibrate_view  # noqa: E402
from calib.camera import angle_between_deg, circle_points_table, make_T, project_points, rotation_from_normal  # noqa: E402
from calib.refine import refine_view  # noqa: E402
from calib.solve_paper import solve_paper  # noqa: E402
from calib.solve_pencil import concentric_conics, fit_edge_conics, solve_pencil  # noqa: E402
from calib.target import TargetSpec  # noqa: E402
from calib.types import CalibrationError, EdgePoints, TargetObservation  # noqa: E402

W, H = 1280, 960
F_TRUE = 3000.0
R1, R2 = 50.0, 28.0
SIGMAS = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0)


def paper_view():
    K = np.array([[F_TRUE, 0, (W - 1) / 2], [0, F_TRUE, (H - 1) / 2], [0, 0, 1.0]])
    n = -np.array([-0.07, 0.93, 0.34])
    T = make_T(rotation_from_normal(n / np.linalg.norm(n)), [-4.3, 41.0, 750.0])
    return K, T


def ring_observation(K, T, points, sigma, rng, sides=(0,), stroke=0.0):
    edges = []
    for R in (R1, R2):
        for side in sides:
            uv = project_points(K, T, circle_points_table(R + side * stroke / 2, points))
            edges.append(EdgePoints(uv + rng.normal(0.0, sigma, uv.shape), R, side))
    return TargetObservation(tuple(edges), W, H)


def errors(f, T_est, T_true):
    """(|df|/f %, normal angle deg, |dT|/|T| %)."""
    t = T_true[:3, 3]
    return (100 * abs(f / F_TRUE - 1), angle_between_deg(T_est[:3, 1], T_true[:3, 1]),
            100 * np.linalg.norm(T_est[:3, 3] - t) / np.linalg.norm(t))


def opencv_chessboard(K, T, sigma, rng):
    """One view of a 9x9-corner, 100 mm board in the table plane; cv2.calibrateCamera."""
    g = np.linspace(-50.0, 50.0, 9)
    X, Z = np.meshgrid(g, g)
    pts_table = np.column_stack([X.ravel(), np.zeros(X.size), Z.ravel()])
    uv = project_points(K, T, pts_table) + rng.normal(0.0, sigma, (len(pts_table), 2))
    board = np.column_stack([X.ravel(), Z.ravel(), np.zeros(X.size)]).astype(np.float32)  # board z = -table Y
    K0 = K.copy()
    K0[0, 0] = K0[1, 1] = 1.25 * F_TRUE
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    _, Kc, _, rv, tv = cv2.calibrateCamera([board], [uv.astype(np.float32)], (W, H), K0, np.zeros(5), flags=flags)
    Rb = cv2.Rodrigues(rv[0])[0]
    T_est = make_T(rotation_from_normal(-Rb[:, 2]), tv[0].ravel())
    return Kc[0, 0], T_est


def solve_all(obs, K):
    """``{solver: (f, T_cam_table)}`` as ``calibrate_view`` computes them (no tilt gate).

    The solvers are called directly so that ``paper``/``pencil`` are not
    followed by the model-check refinement that ``calibrate_view`` runs.
    """
    pp = ((W - 1) / 2, (H - 1) / 2)
    cc = concentric_conics(fit_edge_conics(obs.edges), 0.0)
    out = {"paper": solve_paper(cc, obs.edges, 0.0, pp), "pencil": solve_pencil(cc, pp)}
    K0 = K.copy()
    K0[0, 0] = K0[1, 1] = out["pencil"][0]
    r = refine_view(obs.edges, K0, out["pencil"][1], 0.0)
    out["refine"] = (r.focal_px, r.T_cam_table, r.std.focal_px)
    return out


def noise_table(trials, points, seed):
    K, T = paper_view()
    names = list(SOLVERS) + ["opencv"]
    rows = []
    for si, sigma in enumerate(SIGMAS):
        rng = np.random.default_rng(seed + si)
        err = {n: [] for n in names}
        fails = {n: 0 for n in names}
        sd_f, wins = [], []
        for _ in range(trials):
            obs = ring_observation(K, T, points, sigma, rng)
            try:
                sol = solve_all(obs, K)
            except CalibrationError:
                for s in SOLVERS:
                    fails[s] += 1
                continue
            for s in SOLVERS:
                err[s].append(errors(sol[s][0], sol[s][1], T))
            sd_f.append(100 * sol["refine"][2] / F_TRUE)
            wins.append(err["refine"][-1][0] <= min(err["paper"][-1][0], err["pencil"][-1][0]))
            f_cv, T_cv = opencv_chessboard(K, T, sigma, rng)
            err["opencv"].append(errors(f_cv, T_cv, T))
        med = {n: np.median(np.array(err[n]), axis=0) if err[n] else np.full(3, np.nan) for n in names}
        rms = {n: float(np.sqrt(np.mean(np.array(err[n])[:, 0] ** 2))) for n in names}
        rows.append((sigma, med, float(np.median(sd_f)), 100 * float(np.mean(wins)), fails, rms))
    print(f"### Noise study (paper §5.1 set-up), {trials} trials per sigma, {points} centre-line points per circle\n")
    print("Median relative error of f (%); refine's median reported 1σ of f; share of trials where refine's f "
          "error is the smallest of the three ring solvers.\n")
    print("| σ px | " + " | ".join(f"f % {n}" for n in names) + " | refine σ_f % (reported) | refine best |")
    print("|" + "---|" * (len(names) + 3))
    for sigma, med, sd, win, _, _ in rows:
        print(f"| {sigma:g} | " + " | ".join(f"{med[n][0]:.3f}" for n in names) + f" | {sd:.3f} | {win:.0f} % |")
    print()
    print("Median angle error of the normal (deg) and relative error of T (%).\n")
    print("| σ px | " + " | ".join(f"normal ° {n}" for n in names) + " | "
          + " | ".join(f"T % {n}" for n in names) + " |")
    print("|" + "---|" * (2 * len(names) + 1))
    for sigma, med, _, _, _, _ in rows:
        print(f"| {sigma:g} | " + " | ".join(f"{med[n][1]:.4f}" for n in names) + " | "
              + " | ".join(f"{med[n][2]:.3f}" for n in names) + " |")
    print("\nRMS relative error of f (%) against refine's reported 1σ (the Cramér–Rao bound of the edge data).\n")
    print("| σ px | " + " | ".join(f"f rms % {n}" for n in names) + " | refine σ_f % (reported) |")
    print("|" + "---|" * (len(names) + 2))
    for sigma, _, sd, _, _, rms in rows:
        print(f"| {sigma:g} | " + " | ".join(f"{rms[n]:.3f}" for n in names) + f" | {sd:.3f} |")
    total_fail = {n: sum(r[4][n] for r in rows) for n in names}
    print(f"\nFailed views (all sigmas): {total_fail}\n")


def tilt_table(trials, points, seed, sigma=0.5):
    K = np.array([[F_TRUE, 0, (W - 1) / 2], [0, F_TRUE, (H - 1) / 2], [0, 0, 1.0]])
    print(f"### f against tilt (table normal vs optical axis), σ = {sigma} px, {points} points per circle, "
          f"{trials} trials, refine without the tilt gate\n")
    print("| tilt ° | ray tilt ° | target | median \\|df\\| % | median σ_f % (reported) | failed |")
    print("|---|---|---|---|---|---|")
    for where, t in (("centre", (0.0, 0.0, 750.0)), ("off-centre", (80.0, 60.0, 750.0))):
        for tilt in (2, 4, 6, 8, 10, 15, 20, 30):
            rng = np.random.default_rng(seed + tilt)
            a = np.radians(tilt)
            n = np.array([0.0, -np.sin(a), -np.cos(a)])
            T = make_T(rotation_from_normal(n), t)
            errs, sds, fail = [], [], 0
            for _ in range(trials):
                obs = ring_observation(K, T, points, sigma, rng)
                try:
                    cc = concentric_conics(fit_edge_conics(obs.edges), 0.0)
                    f, T0 = solve_pencil(cc, ((W - 1) / 2, (H - 1) / 2))
                    K0 = K.copy()
                    K0[0, 0] = K0[1, 1] = f
                    r = refine_view(obs.edges, K0, T0, 0.0)
                except CalibrationError:
                    fail += 1
                    continue
                errs.append(100 * abs(r.focal_px / F_TRUE - 1))
                sds.append(100 * r.std.focal_px / F_TRUE)
            ray = angle_between_deg(-n, np.asarray(t))
            print(f"| {tilt} | {ray:.1f} | {where} | {np.median(errs):.2f} | {np.median(sds):.2f} | {fail} |")
    print()


def timing_table(repeats=30, seed=0):
    """Wall and CPU time per call: refine alone on 2000/4000 stroke-edge points, calibrate_view."""
    K, T = paper_view()
    rng = np.random.default_rng(seed)
    print("### Timing (ms per call; CPU = process time, wall = median)\n")
    print("| what | edge points | wall ms | CPU ms |")
    print("|---|---|---|---|")
    for per_edge in (500, 1000):
        obs = ring_observation(K, T, per_edge, 0.5, rng, sides=(-1, 1), stroke=3.45)
        cc = concentric_conics(fit_edge_conics(obs.edges), 3.0)
        f, T0 = solve_pencil(cc, ((W - 1) / 2, (H - 1) / 2))
        K0 = K.copy()
        K0[0, 0] = K0[1, 1] = f
        jobs = [("refine_view", lambda obs=obs, K0=K0, T0=T0: refine_view(obs.edges, K0, T0, 3.0))]
        jobs += [(f"calibrate_view {s}", lambda s=s, obs=obs: calibrate_view(obs, TargetSpec(R1, R2, 3.0), solver=s))
                 for s in SOLVERS]
        for name, job in jobs:
            job()
            wall, cpu0 = [], time.process_time()
            for _ in range(repeats):
                t0 = time.perf_counter()
                job()
                wall.append(time.perf_counter() - t0)
            cpu = (time.process_time() - cpu0) / repeats
            print(f"| {name} | {4 * per_edge} | {1e3 * np.median(wall):.1f} | {1e3 * cpu:.1f} |")
    print()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=1000)
    p.add_argument("--points", type=int, default=360, help="centre-line points per circle (default 360)")
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--tilt-study", action="store_true", help="also tabulate f accuracy against tilt")
    p.add_argument("--no-timing", action="store_true")
    args = p.parse_args(argv)
    print(f"calib_noise.py — {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
          f"{platform.platform()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"numpy {np.__version__}, opencv {cv2.__version__}\n")
    t0 = time.perf_counter()
    noise_table(args.trials, args.points, args.seed)
    if args.tilt_study:
        tilt_table(max(args.trials // 2, 10), args.points, args.seed)
    if not args.no_timing:
        timing_table()
    print(f"(total {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
