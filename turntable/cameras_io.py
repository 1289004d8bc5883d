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
    meta = {k: v for k, v in d.items() if k not in _RESERVED}
    return SequenceCalibration(intrinsics=intr, frames=tuple(frames), mode=str(d.get("mode", "turntable")), meta=meta)


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
