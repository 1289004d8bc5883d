"""``cameras.json``: the public schema of a calibrated sequence.

::

    {"units": "mm",
     "intrinsics": {"K": 3x3, "width": W, "height": H, "dist": [...]},
     "mode": "turntable" | "handheld",
     "frames": [{"image": name, "angle_deg": a, "T_cam_table": 4x4,
                 "rms_px": r, "status": "ok" | "<reason it was skipped>"}],
     ...}

``T_cam_table`` maps table points (mm) into the camera frame (OpenCV axes).
Extra top-level keys (``meta``) are kept on read and written back.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from calib.types import FramePose, Intrinsics, SequenceCalibration
from recon.fileio import atomic_write_bytes

from .errors import UserError

__all__ = ["write_cameras", "read_cameras", "cameras_to_dict", "cameras_from_dict", "atomic_write_text"]

_RESERVED = {"units", "intrinsics", "frames", "mode"}


def _num(x: float):
    x = float(x)
    return None if math.isnan(x) else x


def cameras_to_dict(seq: SequenceCalibration) -> dict:
    intr = seq.intrinsics
    d = {
        "units": "mm",
        "intrinsics": {
            "K": intr.K.tolist(),
            "width": int(intr.width),
            "height": int(intr.height),
            "dist": intr.dist.tolist(),
        },
        "mode": seq.mode,
        "frames": [
            {
                "image": f.image,
                "angle_deg": _num(f.angle_deg),
                "T_cam_table": np.asarray(f.T_cam_table, float).tolist(),
                "rms_px": _num(f.rms_px),
                "status": f.status,
            }
            for f in seq.frames
        ],
    }
    for k, v in seq.meta.items():
        if k not in _RESERVED:
            d[k] = v
    return d


def cameras_from_dict(d: dict, source: str = "cameras.json") -> SequenceCalibration:
    try:
        if d.get("units", "mm") != "mm":
            raise UserError(f"{source}: units must be 'mm', got {d.get('units')!r}")
        i = d["intrinsics"]
        intr = Intrinsics(K=np.asarray(i["K"], float), width=int(i["width"]),
                          height=int(i["height"]), dist=np.asarray(i.get("dist", []), float))
        frames = []
        for k, f in enumerate(d["frames"]):
            T = np.asarray(f["T_cam_table"], float)
            if T.shape != (4, 4):
                raise UserError(f"{source}: frame {k}: T_cam_table must be 4x4, got {T.shape}")
            a = f.get("angle_deg")
            r = f.get("rms_px")
            frames.append(FramePose(image=str(f["image"]), angle_deg=float("nan") if a is None else float(a),
                                    T_cam_table=T, rms_px=float("nan") if r is None else float(r),
                                    status=str(f.get("status", "ok"))))
    except UserError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{source}: not a valid cameras.json ({type(exc).__name__}: {exc})") from None
    _check_sense(intr, frames, source)
    meta = {k: v for k, v in d.items() if k not in _RESERVED}
    return SequenceCalibration(intrinsics=intr, frames=tuple(frames), mode=str(d.get("mode", "turntable")), meta=meta)


def _check_sense(intr: Intrinsics, frames: list[FramePose], source: str) -> None:
    """``UserError`` naming the file, the frame and the reason for cameras no real camera can have.

    A camera matrix with non-finite entries, a focal length that is not
    positive, a last row other than (0, 0, 1), or a non-positive image size;
    non-finite distortion; and, for each frame whose status is "ok" (a failed
    frame keeps a placeholder pose), a non-finite pose, a rotation that is not
    one (orthonormal, determinant +1, to 1e-3), a last row other than
    (0, 0, 0, 1), or a table origin that is not in front of the camera (the
    camera must look at the table: an identity pose puts it at the origin).
    """
    K = intr.K
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise UserError(f"{source}: intrinsics K must be a finite 3x3 matrix, got {K.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise UserError(f"{source}: intrinsics K: the focal lengths must be positive, got fx = {K[0, 0]:g}, "
                        f"fy = {K[1, 1]:g}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise UserError(f"{source}: intrinsics K: the last row must be [0, 0, 1], got {K[2].tolist()}")
    if intr.width <= 0 or intr.height <= 0:
        raise UserError(f"{source}: intrinsics: width and height must be positive, got {intr.width} x {intr.height}")
    if not np.all(np.isfinite(intr.dist)):
        raise UserError(f"{source}: intrinsics dist must be finite, got {intr.dist.tolist()}")
    for k, f in enumerate(frames):
        if not f.ok:
            continue
        T = f.T_cam_table
        where = f"{source}: frame {k} ({f.image})"
        if not np.all(np.isfinite(T)):
            raise UserError(f"{where}: T_cam_table has a non-finite entry (NaN or inf)")
        R = T[:3, :3]
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-3) and abs(np.linalg.det(R) - 1.0) < 1e-3):
            raise UserError(f"{where}: T_cam_table's upper-left 3x3 is not a rotation (orthonormal, determinant +1)")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise UserError(f"{where}: T_cam_table's last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        if not T[2, 3] > 0:
            raise UserError(f"{where}: the table's origin is not in front of the camera (its depth is "
                            f"{T[2, 3]:g} mm): T_cam_table must map table points (mm) into the camera frame "
                            f"(OpenCV: z forward), p_cam = T_cam_table @ p_table")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all (temp file + rename)."""
    atomic_write_bytes(path, text.encode())


def write_cameras(path: str | os.PathLike, seq: SequenceCalibration) -> None:
    atomic_write_text(path, json.dumps(cameras_to_dict(seq), indent=1) + "\n")


def read_cameras(path: str | os.PathLike) -> SequenceCalibration:
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: cannot read cameras file ({exc})") from None
    if not isinstance(d, dict):
        raise UserError(f"{path}: not a valid cameras.json (top level is not an object)")
    return cameras_from_dict(d, source=str(path))
