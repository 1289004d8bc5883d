"""``cameras.json``: the public schema of a calibrated sequence.

::

    {"units": "mm",
     "intrinsics": {"K": 3x3, "width": W, "height": H, "dist": [...]},
     "mode": "turntable" | "handheld",
     "frames": [{"image": name, "angle_deg": a, "T_cam_table": 4x4,
                 "rms_px": r, "status": "ok" | "<reason it was skipped>"}],
     ...}

``T_cam_table`` maps table points (mm) into the camera frame (OpenCV axes).
The calibration's diagnostics (:class:`calib.types.SequenceDiagnostics`) are
top-level keys beside these, one per field (``mode_reason``, ``rms_px``,
``focal_std_px``, ..., ``turntable``: {...}, ``warnings``, ``exif_focal``,
``stage_key``); a file without any of them (``turntable synth``'s ground truth)
has no diagnostics. Other top-level keys are kept on read (``extra``) and
written back.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from calib.types import (
    AngleCheck,
    FramePose,
    Intrinsics,
    SequenceCalibration,
    SequenceDiagnostics,
    TurntableDiagnostics,
)
from recon.fileio import atomic_write_bytes

from .errors import UserError

__all__ = ["write_cameras", "read_cameras", "cameras_to_dict", "cameras_from_dict", "diagnostics_to_dict",
           "diagnostics_from_dict", "atomic_write_text"]

_RESERVED = {"units", "intrinsics", "frames", "mode"}
#: the diagnostics' keys, in the order they are written; the first twelve always are
_DIAGNOSTICS = ("mode_reason", "rms_px", "single_view_rms_px", "frames_used", "frames_skipped", "focal_std_px",
                "principal_point_std_px", "dist_std", "stroke_mm", "stroke_std_mm", "not_estimated",
                "intrinsics_source", "turntable", "angle_checks", "warnings", "exif_focal", "stage_key")


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
    if seq.diagnostics is not None:
        d.update(diagnostics_to_dict(seq.diagnostics))
    for k, v in seq.extra.items():
        if k not in _RESERVED and k not in d:
            d[k] = v
    return d


def diagnostics_to_dict(diag: SequenceDiagnostics) -> dict:
    """The diagnostics' ``cameras.json`` keys: the twelve of every calibration, then ``turntable``,
    ``angle_checks``, ``warnings``, ``exif_focal`` and ``stage_key`` where they have a value."""
    d: dict = {
        "mode_reason": diag.mode_reason,
        "rms_px": diag.rms_px,
        "single_view_rms_px": diag.single_view_rms_px,
        "frames_used": diag.frames_used,
        "frames_skipped": diag.frames_skipped,
        "focal_std_px": diag.focal_std_px,
        "principal_point_std_px": list(diag.principal_point_std_px),
        "dist_std": dict(diag.dist_std),
        "stroke_mm": diag.stroke_mm,
        "stroke_std_mm": diag.stroke_std_mm,
        "not_estimated": dict(diag.not_estimated),
        "intrinsics_source": diag.intrinsics_source,
    }
    tt = diag.turntable
    if tt is not None:
        d["turntable"] = {
            "pattern_offset_from_axis_mm": list(tt.pattern_offset_from_axis_mm),
            "camera_height_mm": tt.camera_height_mm,
            "camera_radius_mm": tt.camera_radius_mm,
            "camera_centres_off_circle_median_mm": tt.camera_centres_off_circle_median_mm,
        }
        if tt.marks_residual_deg is not None:
            d["turntable"]["marks_residual_deg"] = {"median_abs": tt.marks_residual_deg[0],
                                                    "max_abs": tt.marks_residual_deg[1]}
    if diag.angle_checks:
        d["angle_checks"] = [{"image": c.image, "marks_minus_step_deg": c.marks_minus_step_deg}
                             for c in diag.angle_checks]
    if diag.warnings:
        d["warnings"] = list(diag.warnings)
    if diag.exif_focal is not None:
        d["exif_focal"] = dict(diag.exif_focal)
    if diag.stage_key is not None:
        d["stage_key"] = diag.stage_key
    return d


def diagnostics_from_dict(d: dict) -> SequenceDiagnostics | None:
    """The diagnostics in a ``cameras.json`` object (None when it has none of their keys); keys it lacks
    (an older file) are None or empty. Raises KeyError, TypeError or ValueError on malformed values."""
    if not any(k in d for k in _DIAGNOSTICS):
        return None
    tt = d.get("turntable")
    turntable = None
    if tt is not None:
        off = tt["pattern_offset_from_axis_mm"]
        marks = tt.get("marks_residual_deg")
        turntable = TurntableDiagnostics(
            pattern_offset_from_axis_mm=(float(off[0]), float(off[1])),
            camera_height_mm=float(tt["camera_height_mm"]),
            camera_radius_mm=float(tt["camera_radius_mm"]),
            camera_centres_off_circle_median_mm=tt.get("camera_centres_off_circle_median_mm"),
            marks_residual_deg=(float(marks["median_abs"]), float(marks["max_abs"])) if marks else None,
        )
    pp = d.get("principal_point_std_px") or [None, None]
    return SequenceDiagnostics(
        mode_reason=str(d.get("mode_reason", "")),
        rms_px=d.get("rms_px"),
        single_view_rms_px=d.get("single_view_rms_px"),
        frames_used=d.get("frames_used"),
        frames_skipped=d.get("frames_skipped"),
        focal_std_px=d.get("focal_std_px"),
        principal_point_std_px=(pp[0], pp[1]),
        dist_std=dict(d.get("dist_std") or {}),
        stroke_mm=d.get("stroke_mm"),
        stroke_std_mm=d.get("stroke_std_mm"),
        not_estimated=dict(d.get("not_estimated") or {}),
        intrinsics_source=d.get("intrinsics_source"),
        turntable=turntable,
        angle_checks=tuple(AngleCheck(image=str(c["image"]), marks_minus_step_deg=float(c["marks_minus_step_deg"]))
                           for c in d.get("angle_checks") or ()),
        warnings=tuple(str(w) for w in d.get("warnings") or ()),
        exif_focal=d.get("exif_focal"),
        stage_key=d.get("stage_key"),
    )


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
        diagnostics = diagnostics_from_dict(d)
    except UserError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{source}: not a valid cameras.json ({type(exc).__name__}: {exc})") from None
    _check_sense(intr, frames, source)
    extra = {k: v for k, v in d.items() if k not in _RESERVED and k not in _DIAGNOSTICS}
    return SequenceCalibration(intrinsics=intr, frames=tuple(frames), mode=str(d.get("mode", "turntable")),
                               diagnostics=diagnostics, extra=extra)


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
