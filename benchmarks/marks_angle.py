"""Turntable angle from the printed angle marks: accuracy and speed on synthetic scenes.

Scenes come from ``turntable.synth`` (ray-cast object on the printed target,
1280x960, JPEG 95, noise 2 DN) at several elevations and objects. Each frame is
read four ways:

* ``GT pose, yaw randomised``: the true pose turned about the table normal by a
  random angle (what a ring solver returns); the reader must find that angle.
* ``GT pose + 0.05 deg normal, 0.1 % f``: the same with realistic solver errors.
* ``half of the marks hidden``: a half-disc occluder (dark, grey or paper-white)
  painted over half of the target, GT pose.
* ``solver pose``: ``calib.rings.detect_rings`` + ``calib.calibrate.calibrate_view``
  (refine), then the reader; error = yaw of the aligned pose against the truth.

Prints markdown tables. Run: ``nice .venv/bin/python benchmarks/marks_angle.py [--frames 3]``.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.camera import project_points  # noqa: E402
from calib.marks import align_pose_to_marks, read_turntable_angle, turntable_rotation  # noqa: E402
from calib.target import TargetSpec  # noqa: E402
from calib.types import CalibrationError  # noqa: E402
from turntable.synth.sequence import SynthOptions, make_sequence  # noqa: E402

SPEC = TargetSpec(80.0, 50.0, 3.0)
CONDITIONS = ("GT pose, yaw randomised", "GT pose + 0.05 deg normal, 0.1 % f",
              "half of the marks hidden", "solver pose (rings + refine)")


def _wrap(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def _yaw_deg(T_ref: np.ndarray, T: np.ndarray) -> float:
    """Rotation about the table normal between two poses of the same plane, deg."""
    R = T_ref[:3, :3].T @ T[:3, :3]
    return float(np.degrees(np.arctan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2])))


def _perturb(T: np.ndarray, rng: np.random.Generator, normal_err_deg: float) -> np.ndarray:
    n = T[:3, 1]
    axis = rng.normal(size=3)
    axis -= n * (axis @ n)
    axis /= np.linalg.norm(axis)
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(axis * np.radians(normal_err_deg))[0] @ T[:3, :3]
    return out


def _hide_half(img: np.ndarray, K, T, rng) -> np.ndarray:
    th = np.radians(rng.uniform(0, 360) + np.linspace(0.0, 180.0, 91))
    pts = np.vstack([[0.0, 0.0, 0.0], np.column_stack([140 * np.cos(th), 0 * th, 140 * np.sin(th)])])
    poly = np.round(project_points(K, T, pts)).astype(np.int32)
    out = img.copy()
    grey = int(rng.choice([30, 120, 235]))
    cv2.fillPoly(out, [poly], (grey, grey, grey))
    return out


def _read(condition: str, img, K, T_gt, rng):
    """(error deg, AngleReading, read seconds) of one frame under one condition."""
    if condition.startswith("solver"):
        from calib.calibrate import calibrate_view
        from calib.rings import detect_rings

        cal = calibrate_view(detect_rings(img, SPEC), SPEC)
        K, T = cal.intrinsics.K, cal.T_cam_table
        t = time.perf_counter()
        r = read_turntable_angle(img, K, T, SPEC)
        dt = time.perf_counter() - t
        return abs(_yaw_deg(T_gt, align_pose_to_marks(T, r.angle_deg))), r, dt
    alpha = rng.uniform(0, 360)
    T = T_gt @ turntable_rotation(-alpha)
    if condition.startswith("GT pose +"):
        T = _perturb(T, rng, 0.05)
        K = K.copy()
        K[:2, :2] *= 1.001
    if condition.startswith("half"):
        img = _hide_half(img, K, T_gt, rng)
    t = time.perf_counter()
    r = read_turntable_angle(img, K, T, SPEC)
    return abs(_wrap(r.angle_deg - alpha)), r, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3, help="frames per scene (default 3)")
    ap.add_argument("--elevations", type=float, nargs="+", default=[20.0, 30.0, 45.0, 60.0])
    ap.add_argument("--objects", nargs="+", default=["vase", "chair"])
    args = ap.parse_args()
    rng = np.random.default_rng(2026)
    rows = {c: [] for c in CONDITIONS}
    by_elev = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (elev, obj) in enumerate((e, o) for e in args.elevations for o in args.objects):
            out = Path(tmp) / f"s{i}"
            opts = SynthOptions(object=obj, frames=args.frames, step_deg=360.0 / args.frames, jitter_deg=5.0,
                                elevation_deg=elev, distance_mm=450.0 + 100.0 * (elev < 25), seed=i, supersample=2)
            make_sequence(out, opts)
            cams = json.loads((out / "cameras_gt.json").read_text())
            K = np.array(cams["intrinsics"]["K"])
            for fr in cams["frames"]:
                img = cv2.imread(str(out / fr["image"]))
                T_gt = np.array(fr["T_cam_table"])
                for c in CONDITIONS:
                    try:
                        err, r, dt = _read(c, img, K, T_gt, rng)
                        rows[c].append((err, r.coverage, r.n_edges, dt))
                        by_elev.setdefault((c, elev), []).append(err)
                    except CalibrationError as exc:
                        rows[c].append((np.nan, 0.0, 0, np.nan))
                        by_elev.setdefault((c, elev), []).append(np.nan)
                        print(f"  {obj} elev {elev:g} {fr['image']} [{c}]: {exc}", file=sys.stderr)
    print(f"# Angle marks: turntable angle error ({datetime.date.today()}, {platform.machine()}, "
          f"{platform.python_implementation()} {platform.python_version()}, {os.cpu_count()} CPUs)\n")
    print(f"turntable.synth scenes, objects {', '.join(args.objects)}, elevations "
          f"{', '.join(f'{e:g}' for e in args.elevations)} deg, {args.frames} frames each, 1280x960 JPEG 95. "
          f"Bars: median <= 0.1 deg, max <= 0.3 deg.\n")
    print("| condition | read | median err (deg) | p90 (deg) | max (deg) | median coverage | median edges "
          "| median ms |")
    print("|---|---|---|---|---|---|---|---|")
    for c in CONDITIONS:
        a = np.array(rows[c], dtype=float)
        ok = np.isfinite(a[:, 0])
        e = a[ok, 0]
        stats = (f"{np.median(e):.4f} | {np.percentile(e, 90):.4f} | {e.max():.4f}" if e.size else "- | - | -")
        print(f"| {c} | {ok.sum()}/{len(a)} | {stats} | {np.median(a[ok, 1]) if ok.any() else 0:.2f} | "
              f"{np.median(a[ok, 2]) if ok.any() else 0:.0f} | {np.nanmedian(a[:, 3]) * 1e3:.1f} |")
    print("\nMax error (deg) by elevation:\n")
    print("| condition | " + " | ".join(f"{e:g} deg" for e in args.elevations) + " |")
    print("|---|" + "---|" * len(args.elevations))
    for c in CONDITIONS:
        cells = []
        for e in args.elevations:
            v = np.array(by_elev.get((c, e), [np.nan]))
            cells.append(f"{np.nanmax(v):.4f}" + (f" ({np.isnan(v).sum()} failed)" if np.isnan(v).any() else ""))
        print(f"| {c} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
