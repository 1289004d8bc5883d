"""Ring detection speed (and accuracy) on rendered 1280x960 photos of the two-ring target.

Renders 20 frames (elevation 15-75 deg, focal 1000-3000 px, dark / light /
cluttered backdrops, an object hiding up to 40 % of each ring, blur, noise,
uneven light, JPEG 85), then times ``calib.rings.detect_rings`` on each
(``REPEATS`` runs per frame, best-of kept per frame to damp other processes),
split into the coarse search (arcs + ellipses) and the rest. Prints a markdown
table. Run: ``.venv/bin/python benchmarks/detect_speed.py``.
"""

from __future__ import annotations

import datetime
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from synthetic_images import look_at_T, render_target_photo  # noqa: E402

from calib import rings  # noqa: E402
from calib.camera import circle_conic  # noqa: E402
from calib.conics import sampson_distance  # noqa: E402
from calib.target import TargetSpec  # noqa: E402
from calib.types import CalibrationError  # noqa: E402

W, H = 1280, 960
N_FRAMES = 20
REPEATS = 3
SPEC = TargetSpec(r_outer_mm=100.0, r_inner_mm=62.5, stroke_mm=3.0)


def frames(rng):
    for k in range(N_FRAMES):
        elev = 15.0 + 60.0 * k / (N_FRAMES - 1)
        f = float(rng.choice([1000.0, 1800.0, 3000.0]))
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
        dist = 2 * SPEC.r_outer_mm * f / (rng.uniform(0.35, 0.8) * H)
        look = rng.uniform(-20, 20, 2)
        T = look_at_T(elev, rng.uniform(0, 360), dist, look_at_table=(look[0], 0, look[1]),
                      roll_deg=rng.uniform(-20, 20))
        backdrop = ("dark", "light", "clutter")[k % 3]
        photo = render_target_photo(SPEC, K, T, (W, H), rng=rng, backdrop=backdrop, blur_px=0.8,
                                    noise_sigma=2.5, jpeg_quality=85, gain_gradient=0.4)
        yield photo


def timed(fn, *args):
    best_wall, best_cpu, out = np.inf, np.inf, None
    for _ in range(REPEATS):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn(*args)
        best_wall = min(best_wall, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return 1e3 * best_wall, 1e3 * best_cpu, out


def main() -> int:
    rng = np.random.default_rng(2024)
    photos = list(frames(rng))
    wall, cpu, coarse_cpu, errs, fails = [], [], [], [], 0
    for p in photos:
        grey = rings.grey_image(p.image)
        _, cc, _ = timed(rings.coarse_ellipses, grey, 2)
        try:
            w_ms, c_ms, obs = timed(rings.detect_rings, p.image, SPEC)
        except CalibrationError:
            fails += 1
            continue
        wall.append(w_ms)
        cpu.append(c_ms)
        coarse_cpu.append(cc)
        for e in obs.edges:
            C = circle_conic(p.K, p.T_cam_table, e.ring_radius_mm + e.side * SPEC.stroke_mm / 2)
            errs.append(np.median(np.abs(sampson_distance(C, e.uv_px))))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# Ring detection speed, {datetime.date.today()}, {platform.machine()} "
          f"{platform.processor() or platform.platform()}, {os.cpu_count()} CPUs, load {load:.1f}")
    print()
    print("| frames | detected | median ms (wall) | p90 ms (wall) | median ms (CPU) | p90 ms (CPU) "
          "| coarse search ms (CPU) | fine + checks ms (CPU) | median edge error px |")
    print("|---|---|---|---|---|---|---|---|---|")
    fine = np.array(cpu) - np.array(coarse_cpu)
    print(f"| {len(photos)} | {len(photos) - fails} | {np.median(wall):.1f} | {np.percentile(wall, 90):.1f} | "
          f"{np.median(cpu):.1f} | {np.percentile(cpu, 90):.1f} | {np.median(coarse_cpu):.1f} | "
          f"{np.median(fine):.1f} | {np.median(errs):.3f} |")
    print()
    print(f"1280x960, best of {REPEATS} runs per frame; CPU = process time (all threads), the figure to "
          "compare when other processes load the machine (wall time then includes waiting for a core). "
          "Edge error: median over edges of the median |Sampson| distance to the true edge conic.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
