"""Data passed between calibration stages.

Conventions (README "Conventions"): camera frame is OpenCV (x right, y down,
z forward); pixel (0, 0) is the centre of the top-left pixel; the table frame has
its origin at the pattern centre, +Y along the plane normal on the camera's side,
right-handed; lengths in millimetres. ``T_cam_table`` maps table points into the
camera: ``p_cam = T_cam_table @ p_table``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "CalibrationError",
    "Intrinsics",
    "EdgePoints",
    "TargetObservation",
    "RingConics",
    "CalibrationStd",
    "ViewCalibration",
    "FramePose",
    "SequenceCalibration",
    "SequenceDiagnostics",
    "TurntableDiagnostics",
    "AngleCheck",
    "image_centre",
    "as_points",
]


class CalibrationError(Exception):
    """A view (or sequence) cannot be calibrated; the message says why.

    Callers that know the file name prefix it; the message itself names the
    measured reason ("inner ring not found", "view too close to
    fronto-parallel: tilt 3.1 deg, focal length unobservable").
    """


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with optional OpenCV distortion.

    Attributes
    ----------
    K : (3, 3) float64
        Camera matrix ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]`` in pixels, pixel
        centres at integer coordinates.
    width, height : int
        Image size in pixels.
    dist : (n,) float64
        OpenCV distortion coefficients ``k1, k2, p1, p2[, k3]``; empty for none.
    """

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K: expected (3, 3), got {K.shape}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=np.float64).ravel())

    @classmethod
    def from_focal(
        cls,
        focal_px: float,
        width: int,
        height: int,
        principal_point_px: tuple[float, float] | None = None,
        dist=(),
    ) -> Intrinsics:
        """Square pixels, zero skew; principal point at the image centre unless given."""
        cx, cy = principal_point_px if principal_point_px is not None else image_centre(width, height)
        K = np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])
        return cls(K=K, width=int(width), height=int(height), dist=np.asarray(dist, float))

    @property
    def focal_px(self) -> float:
        return float(self.K[0, 0])

    @property
    def principal_point_px(self) -> np.ndarray:
        return self.K[:2, 2].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))


def image_centre(width: int, height: int) -> tuple[float, float]:
    """Centre of a ``width`` x ``height`` image with pixel centres at integers."""
    return (width - 1) / 2.0, (height - 1) / 2.0


def as_points(points, dim: int, name: str) -> np.ndarray:
    """``points`` as (N, ``dim``) float64 rows, OpenCV's (N, 1, ``dim``) squeezed.

    Raises ``ValueError`` naming the argument and the shape received for any
    other shape (a flat array, the transpose, a wrong width), which a bare
    ``reshape(-1, dim)`` would silently reinterpret.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 3 and pts.shape[1] == 1:
        pts = pts[:, 0, :]
    if pts.ndim != 2 or pts.shape[1] != dim:
        raise ValueError(f"{name} must be (N, {dim}), got {np.shape(points)}")
    return pts


@dataclass(frozen=True)
class EdgePoints:
    """Sub-pixel edge points that lie on one printed circle edge.

    The printed ring of centre-line radius ``ring_radius_mm`` is a stroke of
    width w; its two edges are circles of radius ``ring_radius_mm + side * w / 2``.
    ``side`` is +1 for the outer edge, -1 for the inner edge, 0 for points on the
    centre line itself (synthetic data, or a thin-line target).

    Attributes
    ----------
    uv_px : (N, 2) float64
        Image points in pixels (undistorted if the intrinsics carry distortion
        that the caller removed; raw otherwise).
    ring_radius_mm : float
        Centre-line radius of the ring the edge belongs to.
    side : int
        -1, 0 or +1 as above.
    """

    uv_px: np.ndarray
    ring_radius_mm: float
    side: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "uv_px", as_points(self.uv_px, 2, "uv_px"))
        if self.side not in (-1, 0, 1):
            raise ValueError(f"side must be -1, 0 or +1, got {self.side}")

    def radius_mm(self, stroke_mm: float) -> float:
        return self.ring_radius_mm + self.side * stroke_mm / 2.0


@dataclass(frozen=True, eq=False)
class RingConics:
    """Image conics of the two rings: normalised ``C`` (3, 3) float64, pixels, ``x^T C x = 0``.

    Attributes
    ----------
    outer, inner : (3, 3) float64
        The strokes' centre lines.
    outer_plus, outer_minus, inner_plus, inner_minus : (3, 3) float64 or None
        Each stroke's side +1 (outside) and side -1 (inside) edge (None where
        not fitted).
    """

    outer: np.ndarray
    inner: np.ndarray
    outer_plus: np.ndarray | None = None
    outer_minus: np.ndarray | None = None
    inner_plus: np.ndarray | None = None
    inner_minus: np.ndarray | None = None

    def items(self) -> tuple[tuple[str, np.ndarray], tuple[str, np.ndarray]]:
        """The centre lines labelled: ``(("outer", outer), ("inner", inner))`` (for logging)."""
        return ("outer", self.outer), ("inner", self.inner)


@dataclass(frozen=True)
class TargetObservation:
    """Everything one image tells about the two concentric rings.

    Attributes
    ----------
    edges : tuple of EdgePoints
        Edge point sets, any number per ring (typically four: both edges of the
        outer and of the inner ring).
    width, height : int
        Image size in pixels.
    conics : RingConics or None
        The fitted image conics of the rings (diagnostic; None when not
        fitted, or not valid for these edges, e.g. after undistortion).
    """

    edges: tuple[EdgePoints, ...]
    width: int
    height: int
    conics: RingConics | None = None

    def radii_mm(self) -> list[float]:
        return sorted({e.ring_radius_mm for e in self.edges}, reverse=True)


@dataclass(frozen=True)
class CalibrationStd:
    """One-sigma uncertainties of a view calibration (NaN where not estimated)."""

    focal_px: float
    normal_deg: float
    t_mm: np.ndarray  # (3,)
    principal_point_px: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    stroke_mm: float = float("nan")


@dataclass(frozen=True)
class ViewCalibration:
    """Focal length and table pose from one view.

    Attributes
    ----------
    intrinsics : Intrinsics
    T_cam_table : (4, 4) float64
        Table (mm) to camera (mm). Column 1 of its rotation is the table's +Y
        axis (plane normal towards the camera) in camera coordinates; the
        rotation about the normal is arbitrary but right-handed unless the
        angle marks fixed it.
    std : CalibrationStd
    rms_px : float
        RMS geometric residual of the edge points, pixels.
    solver : str
    stroke_mm : float
        Stroke width used (estimated by ``refine``, nominal otherwise).
    """

    intrinsics: Intrinsics
    T_cam_table: np.ndarray
    std: CalibrationStd
    rms_px: float
    solver: str
    stroke_mm: float = float("nan")

    @property
    def R_cam_table(self) -> np.ndarray:
        return self.T_cam_table[:3, :3]

    @property
    def t_cam_table(self) -> np.ndarray:
        return self.T_cam_table[:3, 3]

    @property
    def normal_cam(self) -> np.ndarray:
        return self.T_cam_table[:3, 1]


@dataclass(frozen=True)
class FramePose:
    """One frame of a calibrated sequence (a row of ``cameras.json``).

    Attributes
    ----------
    image : str
        File name of the frame (relative to the input folder).
    angle_deg : float
        Turntable angle of the frame (NaN where unknown).
    T_cam_table : (4, 4) float64
        Table (mm) to camera (mm) for this frame: the turntable rotation is
        folded in, so a point fixed on the object has fixed table coordinates.
    rms_px : float
        RMS edge residual of the frame, pixels (NaN where not calibrated).
    status : str
        ``"ok"`` or the reason the frame was skipped.
    """

    image: str
    angle_deg: float
    T_cam_table: np.ndarray
    rms_px: float = float("nan")
    status: str = "ok"

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class TurntableDiagnostics:
    """What the turntable model found besides the poses (``cameras.json`` key ``turntable``).

    Attributes
    ----------
    pattern_offset_from_axis_mm : (float, float)
        ``(d_x, d_z)``: the printed pattern's centre off the turntable axis, table frame, mm.
    camera_height_mm, camera_radius_mm : float
        The camera centre above the table plane and from the axis, mm.
    camera_centres_off_circle_median_mm : float or None
        The single views' camera centres' median distance from the fitted circle, mm.
    marks_residual_deg : (float, float) or None
        Median and largest ``|yaw|`` between the model's poses and the angle marks', degrees
        (None when no marks were read).
    """

    pattern_offset_from_axis_mm: tuple[float, float]
    camera_height_mm: float
    camera_radius_mm: float
    camera_centres_off_circle_median_mm: float | None
    marks_residual_deg: tuple[float, float] | None = None


@dataclass(frozen=True)
class AngleCheck:
    """A frame whose angle marks disagree with ``--step-deg`` by more than the tolerance, degrees."""

    image: str
    marks_minus_step_deg: float


@dataclass(frozen=True)
class SequenceDiagnostics:
    """How a sequence calibration went: its uncertainties, what it did not estimate and why, warnings.

    Written beside the poses in ``cameras.json`` (one top-level key per field,
    ``turntable.cameras_io``). ``None`` where a value is not known (fixed, or an
    older file without it).

    Attributes
    ----------
    mode_reason : str
        Why the mode (turntable / handheld) was chosen.
    rms_px, single_view_rms_px : float or None
        RMS edge residual of the joint fit, and pooled over the single views, pixels.
    frames_used, frames_skipped : int or None
    focal_std_px : float or None
        1-sigma of ``f``, pixels (None when ``f`` was given).
    principal_point_std_px : (float or None, float or None)
        1-sigma of ``(cx, cy)``, pixels (None where not estimated).
    dist_std : mapping str -> float or None
        1-sigma of each estimated distortion term (``"k1"``, ``"k2"``).
    stroke_mm, stroke_std_mm : float or None
        Estimated stroke width of the printed rings and its 1-sigma, mm.
    not_estimated : mapping str -> str
        Parameter (``"principal_point"``, ``"cx"``, ``"k1"``, ``"distortion"``,
        ``"intrinsics"``, ...) -> why it was not estimated.
    intrinsics_source : str or None
        ``"estimated"`` or ``"given"``.
    turntable : TurntableDiagnostics or None
        Turntable mode only.
    angle_checks : tuple of AngleCheck
        Frames whose marks contradict ``--step-deg``.
    warnings : tuple of str
    exif_focal : mapping or None
        The photos' EXIF focal length against the calibrated one (``turntable.images.exif_focal_report``).
    stage_key : str or None
        The orchestrator's cache key of the calibration that made it (``turntable.stages.cameras``).
    """

    mode_reason: str = ""
    rms_px: float | None = None
    single_view_rms_px: float | None = None
    frames_used: int | None = None
    frames_skipped: int | None = None
    focal_std_px: float | None = None
    principal_point_std_px: tuple[float | None, float | None] = (None, None)
    dist_std: Mapping[str, float | None] = field(default_factory=dict)
    stroke_mm: float | None = None
    stroke_std_mm: float | None = None
    not_estimated: Mapping[str, str] = field(default_factory=dict)
    intrinsics_source: str | None = None
    turntable: TurntableDiagnostics | None = None
    angle_checks: tuple[AngleCheck, ...] = ()
    warnings: tuple[str, ...] = ()
    exif_focal: Mapping[str, Any] | None = None
    stage_key: str | None = None


@dataclass(frozen=True)
class SequenceCalibration:
    """Shared intrinsics and one pose per frame: the content of ``cameras.json``.

    ``diagnostics``: how the calibration went (None for cameras that were not
    calibrated here, e.g. ``turntable synth``'s ground truth); ``extra``: a
    file's other top-level keys (the synthetic scene's ``object``, ``target``,
    ...), kept on read and written back.
    """

    intrinsics: Intrinsics
    frames: tuple[FramePose, ...]
    mode: str = "turntable"  # "turntable" (fixed camera) or "handheld"
    diagnostics: SequenceDiagnostics | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def ok_frames(self) -> tuple[FramePose, ...]:
        return tuple(f for f in self.frames if f.ok)
