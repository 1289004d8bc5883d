"""How light must a printed target's coloured ground be for the ring and mark detectors?

``turntable pattern --background COLOUR`` prints black rings and marks on a
coloured ground. The detectors (``calib.rings``, ``calib.edges``,
``calib.marks``) work on grey levels, so what matters is how much darker the
ink is than the ground. This prints the sheet (PNG, 150 dpi) on grounds from
dark to white -- neutral greys of given relative luminance and a few hues --
photographs it (the sheet's values are taken as reflectances in linear light,
black ink reflecting ``INK`` = 4 %, as laser and inkjet black do; area
supersampling, a light fall-off across the frame, gamma 2.2, shot and read
noise, JPEG 90) from two elevations and two exposures (a normal one, paper at
~80 % of full scale, and a dim one at a third of it, noisier), and runs the
single-view calibration and the angle-mark reader on each photo. It prints
per ground: photos calibrated (rings found, pose solved, marks read), the
worst focal-length error and the worst rotation error of the pose after the
marks' angle is applied (degrees).

``turntable.pattern.MIN_BACKGROUND_LUMINANCE`` (0.35) is set from this table
with a margin. Measured 2026-12-01 (2 cores): neutral grounds of relative
luminance 0.03-0.15 -- 0/4 photos, "no ring found"; 0.20, 0.25, 0.35, 0.50 and
white -- 4/4, worst f error 0.10 %, pose after the marks within 0.005 deg;
green #5bc85b (0.44), blue #6ea8ff (0.39), grey #a6a6a6 (0.38) -- 4/4, f within
0.04 %; a mid blue #3c78d8 (0.19) already lost one photo of four. So the rings
vanish between 0.15 and 0.20 with 4 % ink, and 0.35 leaves about twice that.

Run: ``nice .venv/bin/python benchmarks/target_background.py`` (~1-2 min on 2 cores).
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from calib.calibrate import calibrate_view  # noqa: E402
from calib.camera import look_at, plane_homography  # noqa: E402
from calib.marks import align_pose_to_marks, read_turntable_angle  # noqa: E402
from calib.rings import detect_rings  # noqa: E402
from calib.target import TargetSpec  # noqa: E402
from calib.types import CalibrationError  # noqa: E402
from turntable.pattern import BACKGROUND_COLOURS, _png, relative_luminance, sheet_layout  # noqa: E402

SPEC = TargetSpec(80.0, 50.0, 3.0)
INK = 0.04          # linear reflectance of printed black
DPI = 150.0
W, H, F = 1280, 960, 1400.0


def _grey_of_luminance(y: float) -> tuple[int, int, int]:
    c = y * 12.92 if y <= 0.0031308 else 1.055 * y ** (1 / 2.4) - 0.055
    v = int(round(255 * c))
    return v, v, v


def grounds() -> list[tuple[str, tuple[int, int, int]]]:
    out = [(f"grey Y={y:.2f}", _grey_of_luminance(y)) for y in (0.03, 0.06, 0.1, 0.15, 0.2, 0.25, 0.35, 0.5)]
    out += [(name, rgb) for name, rgb in BACKGROUND_COLOURS.items()]
    out += [("#3c78d8 (mid blue)", (0x3C, 0x78, 0xD8)), ("#2e9e2e (mid green)", (0x2E, 0x9E, 0x2E))]
    return out


def photograph(sheet_rgb: np.ndarray, elevation_deg: float, exposure: float, rng) -> tuple[np.ndarray, np.ndarray,
                                                                                           np.ndarray]:
    """BGR uint8 photo of the printed sheet, its K and true T_cam_table."""
    px = DPI / 25.4
    cx, cy = sheet_layout(SPEC, "a4").centre_mm
    M_table_sheet = np.array([[1 / px, 0, 0.5 / px - cx], [0, 1 / px, 0.5 / px - cy], [0, 0, 1.0]])
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    el, az = np.radians(elevation_deg), rng.uniform(0, 2 * np.pi)
    C = 450.0 * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    T = look_at(C, [0.0, 0.0, 0.0])
    refl = INK + (1.0 - INK) * np.power(sheet_rgb.astype(np.float32) / 255.0, 2.2)  # linear light
    S2 = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])
    big = cv2.warpPerspective(refl, S2 @ plane_homography(K, T) @ M_table_sheet, (2 * W, 2 * H),
                              flags=cv2.INTER_LINEAR, borderValue=(0.02, 0.02, 0.02))
    lin = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    ang = rng.uniform(0, 2 * np.pi)
    gain = exposure * (1.0 - 0.3 * (np.cos(ang) * (xx / W - 0.5) + np.sin(ang) * (yy / H - 0.5) + 0.5))
    lin = lin * gain[..., None]
    dn = 255.0 * np.power(np.clip(lin, 0, 1), 1 / 2.2)
    sigma = np.sqrt(1.0 + 3.0 * dn / 128.0) / np.sqrt(exposure / 0.8)  # dim photos: more gain, more noise
    dn = dn + sigma * rng.standard_normal(dn.shape).astype(np.float32)
    photo = np.clip(np.round(dn), 0, 255).astype(np.uint8)[..., ::-1]  # BGR
    photo = cv2.imdecode(cv2.imencode(".jpg", photo, [cv2.IMWRITE_JPEG_QUALITY, 90])[1], cv2.IMREAD_COLOR)
    return photo, K, T


def measure(rgb: tuple[int, int, int], rng) -> tuple[int, int, float, float]:
    # the PNG writer itself: write_pattern would refuse the grounds below the threshold
    png = _png(SPEC, sheet_layout(SPEC, "a4"), DPI, rgb)
    sheet = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    found, n, f_err, a_err = 0, 0, 0.0, 0.0
    for elevation in (25.0, 45.0):
        for exposure in (0.8, 0.27):
            n += 1
            photo, K, T = photograph(sheet, elevation, exposure, rng)
            try:
                obs = detect_rings(photo, SPEC)
                cal = calibrate_view(obs, SPEC)
                reading = read_turntable_angle(photo, cal.intrinsics.K, cal.T_cam_table, SPEC)
            except (CalibrationError, ValueError):
                f_err = a_err = np.inf
                continue
            found += 1
            f_err = max(f_err, abs(cal.intrinsics.focal_px / F - 1) * 100)
            dR = align_pose_to_marks(cal.T_cam_table, reading.angle_deg)[:3, :3].T @ T[:3, :3]
            a_err = max(a_err, float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))))
    return found, n, f_err, a_err


def _hex(rgb) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def main() -> None:
    rng = np.random.default_rng(3)
    print("| ground | sRGB | relative luminance | photos calibrated | worst f error % "
          "| worst pose error after marks, deg |")
    print("|---|---|---:|---:|---:|---:|")
    for name, rgb in grounds():
        found, n, f_err, a_err = measure(rgb, rng)
        print(f"| {name} | {_hex(rgb)} | {relative_luminance(rgb):.3f} | {found}/{n} | {f_err:.3f} | {a_err:.3f} |",
                  flush=True)


if __name__ == "__main__":
    main()
