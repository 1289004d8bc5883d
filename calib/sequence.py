"""Calibrating a whole sequence: shared intrinsics, and one turntable or one pose per frame.

Pipeline (:func:`calibrate_sequence`): every frame is calibrated on its own
(``calib.calibrate.calibrate_view``) and its rotation about the table normal set
by the angle marks (``calib.marks``); then one of two models is fitted by maximum
likelihood over all frames' ring edge points (:mod:`calib.sequence_model`;
residual: the distance in pixels of each *undistorted* edge point from its
projected edge circle of radius ``R + side * w / 2``, ``w`` the shared stroke width,
i.e. ``calib.refine.edge_residuals``):

* **turntable** (fixed camera, the table turns)::

      T_cam_table_k = T_cam_axis . RotY(theta_k) . Trans(d_x, 0, d_z)

  ``T_cam_axis`` (6 dof) is the camera relative to the turntable axis (axis frame:
  origin where the axis meets the table plane, +Y along the axis), ``d`` (2) the
  printed pattern's offset from the axis (nobody centres the paper exactly),
  ``theta_k`` the turntable angle of frame k (free, or ``k * step_deg`` for a
  motorised table). The rings are symmetric about their centre, so they do not see
  ``theta_k`` (only weakly, through ``d``); the angle marks do. Each frame whose
  marks were read adds one residual: the rotation about the normal between the
  model's pose and the marks-aligned pose, divided by the reading's standard
  deviation and multiplied by the edge noise (both kinds whitened alike). The
  marks are read a second time through the fitted camera and poses, and refitted.
* **handheld** (the camera moves): per-frame normal (2 dof: the rings do not see the
  rotation about it) and centre (3); the rotation about the normal comes from the
  marks, read through the final camera.

"auto" takes the turntable model when the single-view camera centres lie on one
circle about an axis (median distance < 2 % of the camera distance) and its median
frame RMS is within 1.3x (+0.05 px) of the single views'; frames that do not fit
the shared camera (RMS > 4x the median and > 1 px) are dropped and the rest refitted.

Intrinsics: ``f`` always (unless given); the principal point and radial distortion
``k1, k2`` (OpenCV's model, :mod:`calib.distortion`) when the views constrain them.
With a fixed camera every frame sees the same table plane from the same direction,
so every frame images the same circular points and the principal point is
unobservable (the paper's single-view limitation, not lifted by turning the
table): it stays at the image centre, and the result's ``diagnostics`` say so. Otherwise
they are estimated and refused -- kept at their defaults, ``diagnostics.not_estimated``
says why -- when their standard deviation from the Jacobian (``cov = s^2 (J^T J)^-1``)
exceeds :data:`MAX_STD`; ``k1`` then ``k2`` must moreover lower the RMS by
:data:`~calib.sequence_fit.MIN_RMS_GAIN` (else a few 1e-3 of spurious k1 absorb edge-detection bias
and move f).

Angles: ``angle_deg`` is the rotation of the table frame about +Y, right-handed
(``TURN_SIGN``; ``turntable synth``'s convention), 0 at the first frame whose
marks were read (``k * step_deg`` with a step). The table frame of every pose is
the printed one (+X at the 0 deg mark) when the marks were read.

This module holds the entry point, the per-frame stage (single-view calibration and
the marks) and the steps of the sequence (the angles, the mode, the frames left out,
the result); the fits themselves and their thresholds are in :mod:`calib.sequence_fit`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from .calibrate import calibrate_view
from .distortion import undistort_px
from .marks import align_pose_to_marks, read_turntable_angle
from .sequence_fit import (
    FRAME_ERRORS,
    MAX_STD,
    AngleReader,
    FitSetup,
    add_distortion,
    bad_frames,
    choose_mode,
    circle_fit,
    extend_intrinsics,
    fit_handheld,
    fit_turntable,
    reread_marks,
    reread_yaw,
)
from .sequence_model import FitReport, FitState, FitStep, FrameEdges, JointFit, rot_y, wrap_angle, yaw_of
from .target import TargetSpec
from .types import (
    AngleCheck,
    CalibrationError,
    EdgePoints,
    FramePose,
    Intrinsics,
    SequenceCalibration,
    SequenceDiagnostics,
    TargetObservation,
    TurntableDiagnostics,
    image_centre,
)

log = logging.getLogger(__name__)

__all__ = [
    "calibrate_sequence",
    "AngleReader",
    "SingleView",
    "single_view",
    "FitStep",
    "FitReport",
    "marks_angle_reader",
    "expected_pose",
    "rot_y",
    "MAX_STD",
    "TURN_SIGN",
]

#: angle_deg = TURN_SIGN * degrees(theta) with T_cam_table = T_cam_axis . RotY(theta) . Trans(d).
TURN_SIGN = 1.0
#: read the marks a second time through the joint turntable model (see calib.sequence_fit.reread_marks).
REREAD_MARKS = True
#: edge points used by the joint fit, all frames together (see calibrate_sequence).
POINT_BUDGET = 20_000
#: |marks - step| beyond this (deg) is reported per frame.
ANGLE_CHECK_DEG = 1.0


# --------------------------------------------------------------------------- angle marks
def marks_angle_reader(images: Sequence[np.ndarray | None], spec: TargetSpec,
                       dist: np.ndarray | None = None) -> AngleReader:
    """The default :data:`AngleReader`: ``calib.marks`` on ``images[k]`` (raw, distorted by ``dist``)."""
    def read(k: int, K: np.ndarray, T: np.ndarray, dist_now: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        img = images[k]
        if img is None:
            raise CalibrationError("no image to read the angle marks from")
        d = dist_now if dist_now is not None and np.any(dist_now) else dist
        a = read_turntable_angle(img, K, T, spec, dist=d)
        return align_pose_to_marks(T, a.angle_deg), float(a.std_deg)

    return read


# --------------------------------------------------------------------------- a frame between others
def expected_pose(frames: Sequence[FramePose], k: int) -> np.ndarray | None:
    """Frame ``k``'s ``T_cam_table`` as a fixed camera and a turning table predict it from the
    calibrated frames nearest it in the sequence (None with fewer than two).

    Two frames ``a``, ``b`` differ by a turn about the axis: in table
    coordinates ``M = inv(T_a) T_b`` is a rotation by ``phi`` about +Y around the
    axis point ``p`` (``(I - R) p = t`` in X, Z). Frame ``k`` gets the fraction
    ``s = (k - a) / (b - a)`` of that turn (extrapolated before the first and
    after the last): right for an even step, and the rings it is meant to find
    do not depend on the angle at all when the pattern is centred on the axis.
    """
    ok = [i for i, f in enumerate(frames) if f.ok]
    if len(ok) < 2:
        return None
    lo, hi = [i for i in ok if i < k], [i for i in ok if i > k]
    a, b = (lo[-1], hi[0]) if lo and hi else ((hi[0], hi[1]) if len(hi) >= 2 else (lo[-2], lo[-1]))
    Ta = np.asarray(frames[a].T_cam_table, float)
    M = np.linalg.inv(Ta) @ np.asarray(frames[b].T_cam_table, float)
    phi, s = yaw_of(M[:3, :3]), (k - a) / (b - a)
    R = rot_y(s * phi)
    if abs(phi) < 1e-6:
        t = s * M[:3, 3]
    else:
        xz = np.linalg.solve(np.eye(2) - M[:3, :3][np.ix_((0, 2), (0, 2))], M[(0, 2), 3])
        p = np.array([xz[0], 0.0, xz[1]])
        t = p - R @ p
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = R, t
    return Ta @ step


# --------------------------------------------------------------------------- per-frame stage
@dataclass
class SingleView:
    """One frame's single-view result, the joint fit's starting point (:func:`single_view`).

    ``edges``: its edge points, packed for the joint fit; ``T``: its ``T_cam_table``
    (4, 4) mm, yaw aligned to the marks when ``yaw_ok``; ``focal_px``, ``rms_px``,
    ``stroke_mm``: its own fit's; ``angle_std_deg``: the marks' reading 1-sigma;
    ``angle_error``: why the marks were not read ("" when they were).
    """

    edges: FrameEdges
    T: np.ndarray  # single-view pose, yaw aligned to the marks when ``yaw_ok``
    focal_px: float
    rms_px: float
    stroke_mm: float
    yaw_ok: bool = False
    angle_std_deg: float = float("nan")
    angle_error: str = ""


def _undistort_observation(obs: TargetObservation, intr: Intrinsics) -> TargetObservation:
    edges = tuple(EdgePoints(undistort_px(e.uv_px, intr.K, intr.dist), e.ring_radius_mm, e.side)
                  for e in obs.edges)
    return replace(obs, edges=edges, conics=None)


def single_view(obs: TargetObservation, spec: TargetSpec, pp, max_per_edge: int) -> SingleView:
    """Calibrate one frame alone (``calib.calibrate.calibrate_view``, solver "refine", principal point
    ``pp`` or the image centre) and keep at most ``max_per_edge`` points per edge for the joint fit."""
    cal = calibrate_view(obs, spec, solver="refine", principal_point_px=pp)
    stroke = float(cal.stroke_mm) if np.isfinite(cal.stroke_mm) else spec.stroke_mm
    return SingleView(edges=FrameEdges.from_observation(obs, max_per_edge), T=np.asarray(cal.T_cam_table, float),
                      focal_px=cal.intrinsics.focal_px, rms_px=float(cal.rms_px), stroke_mm=stroke)


def _per_frame(observations, spec, intr, pp, reader, failures, max_per_edge, progress):
    """Single-view calibration and mark reading of every frame: ``singles`` (None if failed), reasons."""
    n = len(observations)
    singles: list[SingleView | None] = [None] * n
    reasons = [""] * n
    for k, obs in enumerate(observations):
        if obs is None:
            reasons[k] = (failures[k] if failures is not None and failures[k] else "target rings not found")
        else:
            try:
                if intr is not None:
                    obs = _undistort_observation(obs, intr)
                s = single_view(obs, spec, pp, max_per_edge)
                if reader is not None:
                    K = intr.K if intr is not None else Intrinsics.from_focal(
                        s.focal_px, obs.width, obs.height, pp).K
                    try:
                        T, std = reader(k, K, s.T, None)
                        s.T, s.yaw_ok, s.angle_std_deg = np.asarray(T, float), True, float(std)
                    except FRAME_ERRORS as exc:
                        s.angle_error = str(exc)
                else:
                    s.angle_error = "angle marks not read"
                singles[k] = s
            except FRAME_ERRORS as exc:
                reasons[k] = str(exc)
        if progress is not None:
            progress(k + 1, n)
    return singles, reasons


# --------------------------------------------------------------------------- public entry point
def calibrate_sequence(
    observations: Sequence[TargetObservation | None],
    images: Sequence[np.ndarray | None] | None,
    spec: TargetSpec,
    *,
    names: Sequence[str] | None = None,
    failures: Sequence[str] | None = None,
    step_deg: float | None = None,
    intrinsics: Intrinsics | None = None,
    mode: str = "auto",
    principal_point_px: tuple[float, float] | None = None,
    distortion: str = "auto",
    angle_reader: AngleReader | None = None,
    max_points_per_edge: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    fit_progress: FitReport | None = None,
) -> SequenceCalibration:
    """Shared intrinsics and one pose per frame from a sequence of ring observations.

    Parameters
    ----------
    observations : list of TargetObservation or None
        Ring edges of each frame in turntable order (None where detection failed).
    images : list of (H, W, 3) uint8 BGR or None, or None
        The frames, for the angle marks (``calib.marks``); None: no marks.
    spec : TargetSpec
    names : list of str, optional
        Frame names for the result (default ``frame_000``...).
    failures : list of str, optional
        Why each None observation failed (reported as its status).
    step_deg : float, optional
        Motorised table: frame k is at ``k * step_deg`` (marks, when read, are
        checked against it; disagreements beyond ``ANGLE_CHECK_DEG`` go to ``diagnostics.angle_checks``).
    intrinsics : Intrinsics, optional
        Known camera: edges are undistorted with it and ``K`` is kept.
    mode : {"auto", "turntable", "handheld"}
        Fixed camera and turning table, or a moving camera; "auto" decides from
        the data (camera centres on one circle, joint RMS close to the single views').
    principal_point_px : (2,), optional
        Known principal point (not estimated then).
    distortion : {"auto", "none"}
        "auto": estimate k1, k2 where the views constrain them.
    angle_reader : AngleReader, optional
        Replaces reading the marks from ``images`` (tests, other targets).
    max_points_per_edge : int, optional
        Edge points kept (evenly) per edge for the joint fit; default
        ``POINT_BUDGET / (4 * n_frames)`` within [100, 1000].
    progress : callable(done, total), optional
        Told after each frame's single-view calibration.
    fit_progress : callable(FitStep), optional
        Told the cost of each Levenberg-Marquardt iteration of each stage of
        the joint fit (:class:`FitStep`; ``done`` on a stage's last report).

    Returns
    -------
    SequenceCalibration
        ``mode`` as chosen, per-frame ``status`` ("ok" or the reason), and ``diagnostics``
        with uncertainties, what was not estimated and why, and angle checks.

    Raises
    ------
    CalibrationError
        When no frame can be calibrated (the message lists the reasons).
    ValueError
        For inconsistent arguments.
    """
    n = len(observations)
    if mode not in ("auto", "turntable", "handheld"):
        raise ValueError(f"mode must be auto, turntable or handheld, got {mode!r}")
    if distortion not in ("auto", "none"):
        raise ValueError(f"distortion must be auto or none, got {distortion!r}")
    if images is not None and len(images) != n:
        raise ValueError(f"{len(images)} images for {n} observations")
    names = list(names) if names is not None else [f"frame_{k:03d}" for k in range(n)]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} observations")
    if step_deg is not None and not (np.isfinite(step_deg) and step_deg != 0):
        raise ValueError(f"step_deg must be a non-zero number, got {step_deg}")
    if n == 0:
        raise CalibrationError("no frames")
    if max_points_per_edge is None:
        max_points_per_edge = int(np.clip(POINT_BUDGET / (4 * n), 100, 1000))
    if angle_reader is None and images is not None:
        angle_reader = marks_angle_reader(images, spec, intrinsics.dist if intrinsics is not None else None)
    pp = tuple(intrinsics.principal_point_px) if intrinsics is not None else principal_point_px
    singles, reasons = _per_frame(observations, spec, intrinsics, pp, angle_reader, failures,
                                  max_points_per_edge, progress)
    ok = [k for k in range(n) if singles[k] is not None]
    if not ok:
        summary = "; ".join(sorted({r for r in reasons if r}))
        raise CalibrationError(f"no frame could be calibrated ({summary})")
    obs0 = observations[ok[0]]
    assert obs0 is not None  # a calibrated frame has its observation
    request = _Request(names=names, size=(obs0.width, obs0.height), step_deg=step_deg, intrinsics=intrinsics,
                       mode=mode, principal_point_px=pp, distortion=distortion, reader=angle_reader,
                       report=fit_progress)
    return _calibrate_from_singles(singles, reasons, ok, request)


@dataclass(frozen=True)
class _Request:
    """What :func:`calibrate_sequence` was asked for, as its helpers need it."""

    names: list[str]
    size: tuple[int, int]  # (W, H) pixels
    step_deg: float | None
    intrinsics: Intrinsics | None
    mode: str
    principal_point_px: tuple | None
    distortion: str
    reader: AngleReader | None = None
    report: FitReport | None = None


@dataclass(frozen=True)
class _ModelFit:
    """A fitted model (:func:`_fit_model`): the mode chosen and why, its fit, the frames it used (indices
    into the sequence), the marks-vs-step checks, the camera centres' median distance off the turntable
    circle (mm; NaN without one) and the single views' pooled RMS (px)."""

    mode: str
    why: str
    fit: JointFit
    used: list[int]
    checks: list[AngleCheck]
    centre_rms: float
    rms_pooled: float


def _calibrate_from_singles(singles, reasons, ok, req: _Request) -> SequenceCalibration:
    W, H = req.size
    intr, pp, report = req.intrinsics, req.principal_point_px, req.report
    base: tuple[str, ...]
    if intr is not None:
        K0, base = intr.K.copy(), ()
    else:
        cx, cy = pp if pp is not None else image_centre(W, H)
        f0 = float(np.median([singles[k].focal_px for k in ok]))
        K0, base = np.array([[f0, 0.0, cx], [0.0, f0, cy], [0.0, 0.0, 1.0]]), ("f",)
    free_stroke = any(singles[k].edges.has_stroke for k in ok)
    stroke0 = float(np.median([singles[k].stroke_mm for k in ok])) if free_stroke else 0.0
    state0 = FitState(K=K0, dist=np.zeros(5), stroke=stroke0)
    step_deg, step_note = _step_or_marks(singles, ok, req.names, req.step_deg)
    setup = FitSetup(names=req.names, step_deg=step_deg, state0=state0, base=base, free_stroke=free_stroke,
                     report=report)
    model = _fit_model(singles, ok, req.mode, setup)
    if req.mode == "auto" and model.mode == "handheld":
        model = _retry_turntable(singles, reasons, ok, setup, model)
        ok = [k for k in ok if singles[k] is not None]
    bad = bad_frames(model.fit, model.used)
    if bad and len(model.used) - len(bad) >= 2:
        for k, msg in bad.items():
            singles[k], reasons[k] = None, msg
        ok = [k for k in ok if k not in bad]
        why = model.why + f"; {len(bad)} frame(s) did not fit the shared camera and were dropped"
        model = replace(_fit_model(singles, ok, model.mode, setup), why=why)
    chosen, fit, used = model.mode, model.fit, model.used

    notes: dict[str, str] = {}
    extra: list[str] = []
    if intr is None:
        if pp is not None:
            notes["principal_point"] = "given"
        elif chosen == "turntable":
            notes["principal_point"] = ("not estimated: with a fixed camera every frame sees the table plane "
                                        "from the same direction, so the principal point is unobservable; "
                                        "kept at the image centre")
        else:
            extra += ["cx", "cy"]
        fit = extend_intrinsics(fit, base, tuple(extra), notes, report)
        if req.distortion == "auto":
            fit = add_distortion(fit, notes, report)
        else:
            notes["distortion"] = "not estimated (distortion='none')"
    else:
        notes["intrinsics"] = "given: edges undistorted with them, K kept"
    if req.reader is not None and REREAD_MARKS:
        if chosen == "turntable":
            fit = reread_marks(fit, used, req.reader, report)
        else:
            reread_yaw(fit, used, singles, req.reader)
    why = f"{step_note}; {model.why}" if step_note else model.why
    return _result(replace(model, fit=fit, why=why), singles, reasons, req, notes,
                   warnings=(step_note,) if step_note else ())


def _step_or_marks(singles, ok, names, step_deg) -> tuple[float | None, str]:
    """``(step_deg, "")``, or ``(None, warning)`` when most frames' angle marks contradict the step.

    A wrong ``--step-deg`` (10 for a 30-degree table) fixes every frame at the
    wrong angle: the turntable model cannot fit, and the sequence would fall to
    hand-held mode with a reason that does not name the step. Where the marks
    were read on at least 3 frames and more than half disagree with the step by
    more than ``ANGLE_CHECK_DEG``, the marks are used instead, and the warning
    says so (with the step the marks read).
    """
    if step_deg is None:
        return None, ""
    marked = [k for k in ok if singles[k].yaw_ok]
    if len(marked) < 3:
        return step_deg, ""
    _, _, checks = _initial_angles(singles, marked, names, step_deg)
    if len(checks) <= len(marked) / 2:
        return step_deg, ""
    ref = singles[marked[0]].T[:3, :3]
    rel = [yaw_of(ref.T @ singles[k].T[:3, :3]) for k in marked]
    per_frame = [math.degrees(float(wrap_angle(b - a))) * TURN_SIGN / (kb - ka)
                 for a, b, ka, kb in zip(rel[:-1], rel[1:], marked[:-1], marked[1:], strict=True)]
    read = float(np.median(per_frame))
    return None, (f"--step-deg {step_deg:g} contradicts the angle marks on {len(checks)} of {len(marked)} frames "
                  f"(they read {read:.1f}° per frame): the marks were used instead of the step")


def _retry_turntable(singles, reasons, ok, setup: FitSetup, first: _ModelFit) -> _ModelFit:
    """Auto mode chose hand-held: is it one odd frame (upside down, the camera bumped)?

    The frames whose camera centre lies far off the circle the others share
    (:func:`circle_fit`; at most a tenth of them, at least one) are left out
    and the mode chosen again. If the rest is a turntable sequence, they are
    marked as not calibrated with the reason and the turntable model is kept;
    otherwise the first, hand-held, result stands, and its reason says that
    the sequence looked like a turntable but did not fit one.
    """
    have_step = setup.step_deg is not None
    angled = [k for k in ok if singles[k].yaw_ok or have_step]
    if len(angled) < 4:
        return first
    theta_all, _, _ = _initial_angles(singles, angled, setup.names, setup.step_deg)
    _, per_frame, rows = circle_fit([singles[k].T for k in angled], [theta_all[k] for k in angled])
    odd = [k for k, r in zip(angled, rows, strict=True) if not r]
    if odd and len(odd) <= max(1, len(angled) // 10):
        rest = [k for k in ok if k not in odd]
        trial = _fit_model(singles, rest, "auto", setup)
        if trial.mode == "turntable":
            for k, off in zip(angled, per_frame, strict=True):
                if k in odd:
                    singles[k] = None
                    reasons[k] = (f"does not fit the turntable: its camera is {off:.0f} mm off the circle the "
                                  f"other frames' cameras share (upside down, or the camera moved?)")
            return replace(trial, why=trial.why + f"; {len(odd)} frame(s) off the turntable circle left out")
    return replace(first, why=first.why + ("; the angle marks were read, so this looked like a turntable: if it "
                                           "is one, look for frames that do not belong (or use --mode turntable)"
                                           if len(angled) >= 3 else ""))


def _fit_model(singles, ok, mode: str, setup: FitSetup) -> _ModelFit:
    """Fit the turntable model where possible, choose the mode, fit the handheld model if chosen."""
    step_deg = setup.step_deg
    have_step = step_deg is not None
    angled = [k for k in ok if singles[k].yaw_ok or have_step]
    rms_pooled = float(np.sqrt(np.mean([singles[k].rms_px ** 2 for k in ok])))
    distance = float(np.median([np.linalg.norm(singles[k].T[:3, 3]) for k in ok]))
    fit_tt, centre_rms, checks = None, float("nan"), list[AngleCheck]()
    if mode == "turntable" and not angled:
        raise CalibrationError("turntable mode needs the turntable angle of each frame: the angle marks "
                               "could not be read in any frame and no step was given")
    if mode == "turntable" or (mode == "auto" and len(angled) >= 3):
        theta_all, free_theta, checks = _initial_angles(singles, angled, setup.names, step_deg)
        yaw_known = any(singles[k].yaw_ok for k in angled)
        theta0 = np.array([theta_all[k] for k in angled])
        try:
            fit_tt, centre_rms = fit_turntable(singles, angled, setup, theta0, free_theta, yaw_known, rms_pooled)
        except (np.linalg.LinAlgError, ValueError) as exc:
            log.warning("turntable fit failed: %s", exc)
    chosen, why = choose_mode(mode, singles, ok, angled, fit_tt, centre_rms, distance)
    if chosen == "turntable":
        if fit_tt is None:
            raise CalibrationError("turntable model could not be fitted")
        return _ModelFit(chosen, why, fit_tt, angled, checks, centre_rms, rms_pooled)
    fit = fit_handheld(singles, ok, setup)
    return _ModelFit(chosen, why, fit, ok, checks, centre_rms, rms_pooled)


def _initial_angles(singles, angled, names, step_deg):
    """Initial theta (rad, dict by frame), which are free, and marks-vs-step checks."""
    have_step = step_deg is not None
    theta: dict[int, float] = {}
    checks: list[AngleCheck] = []
    marked = [k for k in angled if singles[k].yaw_ok]
    ref = marked[0] if marked else angled[0]
    for k in angled:
        if have_step:
            theta[k] = math.radians(k * step_deg) / TURN_SIGN
        else:
            theta[k] = yaw_of(singles[ref].T[:3, :3].T @ singles[k].T[:3, :3])
    if have_step and marked:
        for k in marked:
            rel = yaw_of(singles[ref].T[:3, :3].T @ singles[k].T[:3, :3])
            diff = math.degrees(float(wrap_angle(rel - (theta[k] - theta[ref]))))
            if abs(diff) > ANGLE_CHECK_DEG:
                checks.append(AngleCheck(image=names[k], marks_minus_step_deg=round(diff, 3)))
    free = np.array([(not have_step) and k != ref for k in angled])
    return theta, free, checks


def _num(x) -> float | None:
    x = float(x)
    return None if not math.isfinite(x) else x


def _result(model: _ModelFit, singles, reasons, req: _Request, notes: dict[str, str],
            warnings: tuple[str, ...] = ()) -> SequenceCalibration:
    fit, mode, used, intr = model.fit, model.mode, model.used, req.intrinsics
    st = fit.state
    W, H = req.size
    names = req.names
    if intr is not None:
        intrinsics = Intrinsics(K=intr.K, width=W, height=H, dist=intr.dist)
    else:
        dist = st.dist if np.any(st.dist) else np.zeros(0)
        intrinsics = Intrinsics(K=st.K, width=W, height=H, dist=dist)
    Ts = st.poses()
    pos = {k: i for i, k in enumerate(used)}
    frames = []
    for k in range(len(singles)):
        s = singles[k]
        if k in pos:
            i = pos[k]
            # st.theta is set in turntable mode, the only one that reads it
            angle = (TURN_SIGN * math.degrees(st.theta[i])) % 360.0 if mode == "turntable" else float("nan")  # type: ignore[index]
            status = "ok" if (mode == "turntable" or s.yaw_ok) else f"angle marks unreadable: {s.angle_error}"
            frames.append(FramePose(image=names[k], angle_deg=angle, T_cam_table=Ts[i],
                                    rms_px=float(fit.rms_per_frame[i]), status=status))
        else:
            reason = reasons[k] if s is None else f"angle marks unreadable: {s.angle_error}"
            frames.append(FramePose(image=names[k], angle_deg=float("nan"), T_cam_table=np.eye(4),
                                    status=reason or "not calibrated"))
    std = fit.std
    turntable = None
    if mode == "turntable":
        assert st.R_cam_axis is not None and st.d_xz is not None and st.t_cam_axis is not None
        C = -st.R_cam_axis.T @ st.t_cam_axis
        p = fit.problem
        res = [math.degrees(p.mark_residual(i, Ts[i][:3, :3]) / p.mark_w[i])
               for i in range(len(used)) if p.has_mark[i]]
        turntable = TurntableDiagnostics(
            pattern_offset_from_axis_mm=(float(st.d_xz[0]), float(st.d_xz[1])),
            camera_height_mm=float(C[1]),
            camera_radius_mm=float(np.hypot(C[0], C[2])),
            camera_centres_off_circle_median_mm=_num(model.centre_rms),
            marks_residual_deg=(float(np.median(np.abs(res))), float(np.max(np.abs(res)))) if res else None,
        )
    diagnostics = SequenceDiagnostics(
        mode_reason=model.why,
        rms_px=fit.rms_px,
        single_view_rms_px=model.rms_pooled,
        frames_used=len(used),
        frames_skipped=sum(1 for f in frames if not f.ok),
        focal_std_px=_num(std.get("f", float("nan"))),
        principal_point_std_px=(_num(std.get("cx", float("nan"))), _num(std.get("cy", float("nan")))),
        dist_std={k: _num(std[k]) for k in ("k1", "k2") if k in std},
        stroke_mm=_num(st.stroke) if fit.problem.free_stroke else None,
        stroke_std_mm=_num(std.get("stroke", float("nan"))),
        not_estimated=notes,
        intrinsics_source="given" if intr is not None else "estimated",
        turntable=turntable,
        angle_checks=tuple(model.checks),
        warnings=warnings,
    )
    return SequenceCalibration(intrinsics=intrinsics, frames=tuple(frames), mode=mode, diagnostics=diagnostics)
