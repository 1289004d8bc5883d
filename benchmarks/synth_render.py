"""Rendering speed and anti-aliasing quality of ``turntable synth`` (1280x960 frames).

Renders the default scene (vase on the printed target, dark backdrop, f 1500 px,
30 deg elevation, 450 mm) and prints a markdown table: seconds per frame for
adaptive supersampling at s = 1..4 (edge pixels only) and for brute-force 3x3
supersampling of every pixel, side by side in one run, with the share of pixels
that got extra rays and the difference to the brute-force image (8-bit DN).
The whole 36-frame ``make_sequence`` is timed too (``--skip-sequence`` to omit).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.camera import invert_T  # noqa: E402
from turntable.synth import render as R  # noqa: E402
from turntable.synth.objects import make_object  # noqa: E402
from turntable.synth.sequence import SynthOptions, camera_poses, make_sequence  # noqa: E402


def _brute_force(scene, K, T, size, s):
    """Every pixel with s x s rays (the reference the adaptive renderer approximates)."""
    W, H = size
    vv, uu = np.mgrid[0:H, 0:W]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    lin, cover, _ = R._render_pixels(scene, K, None, uv, s, invert_T(T), np.eye(4), R._light_dirs(scene, s * s))
    return R._encode_srgb(lin).reshape(H, W, 3), (cover >= 0.5).reshape(H, W)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3, help="frames timed per setting (default 3)")
    ap.add_argument("--skip-sequence", action="store_true", help="do not time the 36-frame sequence")
    args = ap.parse_args()

    opts = SynthOptions()
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    mesh = make_object("vase", rng)
    scene = R.build_scene(mesh, opts.target_spec(), "dark", rng=rng, target_px_per_mm=6.5,
                          backdrop_distance_mm=240.0)
    t_build = time.perf_counter() - t
    K = opts.intrinsics().K
    size = (opts.width, opts.height)
    _, poses, _ = camera_poses(opts, 110.0, np.random.default_rng(1))

    t = time.perf_counter()
    ref, ref_mask = _brute_force(scene, K, poses[0], size, 3)
    t_brute = time.perf_counter() - t

    rows = []
    for s in (1, 2, 3, 4):
        times = []
        for k in range(args.frames):
            t = time.perf_counter()
            img, mask = R.render_view(scene, K, poses[k], size, supersample=s)
            times.append(time.perf_counter() - t)
            if k == 0:
                diff = np.abs(img.astype(int) - ref.astype(int))
                mask_diff = int((mask != ref_mask).sum())
        lin, _, cls = R._render_pixels(scene, K, None, np.column_stack(
            [np.tile(np.arange(size[0]), size[1]), np.repeat(np.arange(size[1]), size[0])]).astype(float),
            1, invert_T(poses[0]), np.eye(4), R._light_dirs(scene, 1))
        aa = R._needs_aa(cls.reshape(size[1], size[0]), R._encode_srgb(lin).reshape(size[1], size[0], 3) / 255.0)
        rows.append((f"adaptive, s = {s}", float(np.median(times)), aa.mean() if s > 1 else 0.0,
                     diff.mean(), np.percentile(diff, 99.9), diff.max(), mask_diff))
    rows.append(("brute force 3x3, every pixel", t_brute, 1.0, 0.0, 0.0, 0, 0))

    t_seq = float("nan")
    if not args.skip_sequence:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            make_sequence(Path(tmp) / "seq", opts)
            t_seq = time.perf_counter() - t

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# turntable synth rendering ({datetime.date.today()}, {platform.machine()}, "
          f"{os.cpu_count()} CPUs, load {load:.1f}, {platform.python_version()})\n")
    print(f"1280x960, vase ({len(mesh.faces)} triangles), scene build {t_build:.2f} s. "
          "Differences are to the brute-force 3x3 image of the same frame (8-bit DN).\n")
    print("| rendering | s / frame | x brute force | pixels supersampled | mean abs diff | 99.9 % diff "
          "| max diff | mask pixels differing |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, sec, frac, mean, p999, mx, md in rows:
        print(f"| {name} | {sec:.2f} | {sec / t_brute:.2f} | {100 * frac:.1f} % | {mean:.3f} | {p999:.1f} "
              f"| {mx} | {md} |")
    if not args.skip_sequence:
        print(f"\nWhole default sequence (36 frames, s = 3, noise, JPEG 95): {t_seq:.1f} s "
              f"({t_seq / 36:.2f} s / frame).")


if __name__ == "__main__":
    main()
