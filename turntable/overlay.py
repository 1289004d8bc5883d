"""Diagnostic drawings: what the calibration saw and what it concluded."""

from __future__ import annotations

import contextlib

import cv2
import numpy as np

from calib.camera import circle_points_table, project_points
from calib.conics import conic_to_ellipse, ellipse_points
from calib.types import TargetObservation, ViewCalibration

__all__ = ["draw_calibration"]

_SHIFT = 4  # sub-pixel drawing: coordinates scaled by 2**4


def _poly(img, uv, color, thickness=1, closed=True):
    pts = np.round((np.asarray(uv) + 0.0) * (1 << _SHIFT)).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(img, [pts], closed, color, thickness, cv2.LINE_AA, _SHIFT)


def draw_calibration(image_bgr: np.ndarray, obs: TargetObservation | None, cal: ViewCalibration | None,
                     r_outer_mm: float, r_inner_mm: float, label: str = "") -> np.ndarray:
    """Overlay: edge points (yellow), fitted conics (cyan), re-projected rings
    (magenta), projected centre and table axes (X red, Y=normal green, Z blue)."""
    img = image_bgr.copy()
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    thick = max(1, int(round(max(img.shape[:2]) / 900)))
    if obs is not None:
        for e in obs.edges:
            for u, v in e.uv_px[:: max(1, len(e.uv_px) // 400)]:
                cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 16, (0, 220, 255), -1, cv2.LINE_AA, 4)
        for C in (obs.conics.outer, obs.conics.inner) if obs.conics is not None else ():
            with contextlib.suppress(ValueError):
                _poly(img, ellipse_points(conic_to_ellipse(C), 360), (255, 255, 0), thick)
    if cal is not None:
        K, T = cal.intrinsics.K, cal.T_cam_table
        for r in (r_outer_mm, r_inner_mm):
            _poly(img, project_points(K, T, circle_points_table(r, 360)), (255, 0, 255), thick)
        L = 0.8 * r_inner_mm
        o, x, y, z = project_points(K, T, np.array([[0, 0, 0], [L, 0, 0], [0, L, 0], [0, 0, L]], float))
        for tip, col in ((x, (0, 0, 255)), (y, (0, 200, 0)), (z, (255, 0, 0))):
            cv2.arrowedLine(img, tuple(np.round(o).astype(int)), tuple(np.round(tip).astype(int)), col,
                            2 * thick, cv2.LINE_AA, tipLength=0.08)
        cv2.drawMarker(img, tuple(np.round(o).astype(int)), (0, 0, 255), cv2.MARKER_CROSS, 20 * thick, thick)
        s = cal.std
        label = (f"{label}  f = {cal.intrinsics.focal_px:.1f} +/- {s.focal_px:.1f} px   "
                 f"rms {cal.rms_px:.2f} px   [{cal.solver}]").strip()
    if label:
        scale, org = 0.6 * thick, (12, int(30 * thick))
        (w, h), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
        cv2.rectangle(img, (org[0] - 6, org[1] - h - 6), (org[0] + w + 6, org[1] + base + 6), (0, 0, 0), -1)
        cv2.putText(img, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return img
