"""``turntable calibrate``: focal length and table pose from single photos.

Each image is calibrated on its own (detection -> solver). A failing image is
reported by name and reason on stderr (and in the JSON), the others are still
processed, and the exit code is 1 if any image failed.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from calib.camera import angle_between_deg
from calib.target import TargetSpec
from calib.types import CalibrationError, TargetObservation, ViewCalibration

from ..errors import UserError
from ..images import exif_focal_report, focal_warning, read_image
from .args import add_target_arguments, target_from_args

log = logging.getLogger(__name__)

SOLVERS = ("paper", "pencil", "refine")


def add_arguments(parser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="photos of the two-ring target")
    add_target_arguments(parser)
    parser.add_argument("--solver", choices=SOLVERS, default="refine",
                        help="paper: the paper as written; pencil: closed form from the conic pencil; "
                             "refine (default): maximum likelihood over all edge points")
    parser.add_argument("--principal-point", type=float, nargs=2, metavar=("U", "V"),
                        help="principal point in pixels (default: image centre)")
    parser.add_argument("--json", action="store_true", help="print JSON (an object for one image, a list for several)")
    parser.add_argument("--overlay", metavar="DIR", help="write <image>_overlay.png per image into DIR")


def calibration_record(image: str, cal: ViewCalibration) -> dict:
    """The public JSON record of one calibrated image."""
    R, t = cal.R_cam_table, cal.t_cam_table
    tilt = angle_between_deg(cal.normal_cam, -t)

    def num(x):
        x = float(x)
        return None if math.isnan(x) else x

    return {
        "image": image,
        "status": "ok",
        "focal_px": cal.intrinsics.focal_px,
        "principal_point_px": cal.intrinsics.principal_point_px.tolist(),
        "width": cal.intrinsics.width,
        "height": cal.intrinsics.height,
        "R_cam_table": R.tolist(),
        "t_cam_table_mm": t.tolist(),
        "normal_cam": cal.normal_cam.tolist(),
        "tilt_deg": tilt,
        "stroke_mm": num(cal.stroke_mm),
        "std": {
            "focal_px": num(cal.std.focal_px),
            "normal_deg": num(cal.std.normal_deg),
            "t_mm": [num(v) for v in np.asarray(cal.std.t_mm).ravel()],
            "stroke_mm": num(cal.std.stroke_mm),
        },
        "rms_px": float(cal.rms_px),
        "solver": cal.solver,
    }


def calibrate_file(path: Path, spec: TargetSpec, solver: str, principal_point):
    """Read, detect and solve one image. Returns (image_bgr, observation, calibration)."""
    from calib.calibrate import calibrate_view
    from calib.rings import detect_rings

    img = read_image(path)
    obs = None
    try:
        obs = detect_rings(img, spec)
        cal = calibrate_view(obs, spec, solver=solver, principal_point_px=principal_point)
    except CalibrationError as exc:
        raise _ImageFailure(img, obs, str(exc)) from None
    return img, obs, cal


class _ImageFailure(Exception):
    def __init__(self, img, obs: TargetObservation | None, reason: str):
        super().__init__(reason)
        self.img, self.obs, self.reason = img, obs, reason


def _table(records: list[dict]) -> str:
    head = f"{'image':<28} {'f [px]':>9} {'±1σ':>6} {'tilt':>6} {'|t| mm':>8} {'rms px':>7}  status"
    lines = [head, "-" * len(head)]
    for r in records:
        name = Path(r["image"]).name[:28]
        if r["status"] != "ok":
            lines.append(f"{name:<28} {'':>9} {'':>6} {'':>6} {'':>8} {'':>7}  {r['error']}")
            continue
        sf = r["std"]["focal_px"]
        lines.append(f"{name:<28} {r['focal_px']:9.1f} {sf if sf is not None else float('nan'):6.1f} "
                     f"{r['tilt_deg']:5.1f}° {np.linalg.norm(r['t_cam_table_mm']):8.1f} {r['rms_px']:7.3f}  ok")
    return "\n".join(lines)


def run(args) -> int:
    spec = target_from_args(args)
    overlay_dir = Path(args.overlay) if args.overlay else None
    if overlay_dir is not None:
        if overlay_dir.exists() and not overlay_dir.is_dir():
            raise UserError(f"--overlay {overlay_dir}: exists and is not a folder")
        overlay_dir.mkdir(parents=True, exist_ok=True)
    pp = tuple(args.principal_point) if args.principal_point else None
    records, failed = [], 0
    for name in args.images:
        path = Path(name)
        t0 = time.perf_counter()
        img = obs = cal = None
        try:
            img, obs, cal = calibrate_file(path, spec, args.solver, pp)
            rec = calibration_record(str(path), cal)
            intr = cal.intrinsics
            exif = exif_focal_report([path], intr.width, intr.height, intr.focal_px)
            rec["exif_focal_px"] = exif["focal_px"] if exif else None
            warning = focal_warning(intr.focal_px, exif)
            if warning:
                print(f"turntable calibrate: {path}: warning: {warning}", file=sys.stderr)
        except UserError as exc:  # unreadable file: message already names it
            rec = {"image": str(path), "status": "error", "error": str(exc).split(": ", 1)[-1]}
        except _ImageFailure as exc:
            img, obs = exc.img, exc.obs
            rec = {"image": str(path), "status": "error", "error": exc.reason}
        except Exception as exc:  # a bug on one image must not lose the others' results
            if getattr(args, "verbose", 0) >= 2:
                raise
            rec = {"image": str(path), "status": "error",
                   "error": f"internal error: {type(exc).__name__}: {exc} (run with -vv for the traceback)"}
        if rec["status"] != "ok":
            failed += 1
            print(f"turntable calibrate: {path}: {rec['error']}", file=sys.stderr)
        log.info("%s: %.1f ms", path, 1e3 * (time.perf_counter() - t0))
        records.append(rec)
        if overlay_dir is not None and img is not None:
            from ..overlay import draw_calibration

            out = draw_calibration(img, obs, cal, spec.r_outer_mm, spec.r_inner_mm,
                                   label=path.name if cal is not None else f"{path.name}: {rec.get('error')}")
            target = overlay_dir / f"{path.stem}_overlay.png"
            ok, buf = cv2.imencode(".png", out)
            if ok:
                tmp = target.with_suffix(".png.tmp")
                buf.tofile(str(tmp))
                tmp.replace(target)
    if args.json:
        print(json.dumps(records[0] if len(records) == 1 else records, indent=1))
    else:
        print(_table(records))
    return 1 if failed else 0
