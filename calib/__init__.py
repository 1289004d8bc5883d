"""calib: single-view and sequence calibration from two concentric printed rings.

Edges, ellipses and conics -> ring detection -> the paper's solver, the conic
pencil's closed form, maximum-likelihood refinement -> the turntable angle
from the printed marks -> one joint calibration per sequence. Both
maximum-likelihood fits (``refine``, ``sequence_model``) are solved by the one
Levenberg-Marquardt solver of ``lm`` (soft-L1 or least squares).

Public names are imported lazily (``from calib import detect_rings`` loads only
what it needs).
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "types": ["CalibrationError", "Intrinsics", "EdgePoints", "TargetObservation", "RingConics", "CalibrationStd",
              "ViewCalibration", "FramePose", "SequenceCalibration", "SequenceDiagnostics",
              "TurntableDiagnostics", "AngleCheck", "image_centre"],
    "target": ["TargetSpec"],
    "camera": ["make_T", "invert_T", "rotation_from_normal", "plane_homography", "circle_conic", "project_points",
               "circle_points_table", "camera_centre_table", "angle_between_deg"],
    "conics": ["Ellipse", "fit_conic", "conic_to_ellipse", "ellipse_to_conic", "sampson_distance"],
    "rings": ["detect_rings", "pencil_ratio"],
    "calibrate": ["calibrate_view", "tilt_deg", "SOLVERS", "MIN_TILT_DEG"],
    "solve_paper": ["solve_paper"],
    "solve_pencil": ["solve_pencil"],
    "refine": ["refine_view", "edge_residuals"],
    "marks": ["AngleReading", "read_turntable_angle", "align_pose_to_marks", "turntable_rotation"],
    "sequence": ["calibrate_sequence"],
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module 'calib' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
