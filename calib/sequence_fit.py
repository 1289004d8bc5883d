"""The fits behind :func:`calib.sequence.calibrate_sequence`, and the thresholds they use.

The models, their residuals and the conventions are described in :mod:`calib.sequence`;
the joint problem and its solver are :mod:`calib.sequence_model`. Here:

* the turntable model's starting point from the single-view poses: the camera
  centres on one circle about the axis (:func:`circle_fit`);
* the turntable and hand-held fits of a set of frames (:func:`fit_turntable`,
  :func:`fit_handheld`, from a :class:`FitSetup`);
* which optional intrinsics the views constrain (:func:`extend_intrinsics`,
  :func:`add_distortion`; :data:`MAX_STD`, :data:`MIN_RMS_GAIN`);
* what "auto" chooses (:func:`choose_mode`; :data:`MODE_CENTRE_TOL`,
  :data:`MODE_RMS_RATIO`) and which frames do not fit the shared camera
  (:func:`bad_frames`; :data:`BAD_FRAME_RATIO`, :data:`BAD_FRAME_MIN_PX`);
* the angle marks read again through the fitted camera (:func:`reread_marks`,
  :func:`reread_yaw`; :data:`AngleReader`).

``singles`` below is the list of :class:`calib.sequence.SingleView` (None where a
frame failed) and ``idx``/``used`` the frames fitted, as indices into it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from .camera import camera_centre_table, make_T, rotation_from_normal
from .sequence_model import (
    FitReport,
    FitState,
    JointFit,
    JointProblem,
    fit_joint,
    project_rotation,
    rot_y,
    solve_joint,
)
from .types import CalibrationError

__all__ = [
    "AngleReader",
    "FRAME_ERRORS",
    "FitSetup",
    "circle_fit",
    "fit_turntable",
    "fit_handheld",
    "extend_intrinsics",
    "add_distortion",
    "choose_mode",
    "bad_frames",
    "reread_marks",
    "reread_yaw",
    "MAX_STD",
    "MIN_RMS_GAIN",
    "BAD_FRAME_RATIO",
    "BAD_FRAME_MIN_PX",
    "MODE_RMS_RATIO",
    "MODE_CENTRE_TOL",
]

#: Largest 1-sigma accepted for an optional intrinsic parameter; beyond it the
#: views do not constrain it and it is kept at its default.
MAX_STD = {"cx": 2.0, "cy": 2.0, "k1": 0.005, "k2": 0.01}
#: distortion terms kept only when they lower the RMS edge residual by this fraction.
MIN_RMS_GAIN = 0.03
#: a frame whose RMS under the shared model exceeds this many times the median (and BAD_FRAME_MIN_PX)
#: is dropped (a misdetection, or a camera that moved).
BAD_FRAME_RATIO = 4.0
BAD_FRAME_MIN_PX = 1.0
#: turntable model accepted when its RMS is within this factor (+0.05 px) of the single-view fits'.
MODE_RMS_RATIO = 1.3
#: turntable model considered when the camera centres fit one circle within this fraction of the distance.
MODE_CENTRE_TOL = 0.02

#: what one frame's single-view solve or mark reading may raise without stopping the sequence
#: (a degenerate fit deep inside a solver surfaces as ValueError/LinAlgError).
FRAME_ERRORS = (CalibrationError, ValueError, np.linalg.LinAlgError)

#: ``reader(frame_index, K, T_cam_table, dist) -> (T_cam_table_aligned, std_deg)``: the pose rotated
#: about the table normal so that table +X points at the printed 0 deg mark; ``dist`` (OpenCV
#: coefficients of the raw image, or None); raises CalibrationError.
AngleReader = Callable[[int, np.ndarray, np.ndarray, "np.ndarray | None"], tuple[np.ndarray, float]]


# --------------------------------------------------------------------------- initialisation
def circle_fit(Ts: list[np.ndarray], theta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera centres on one circle about the axis: ``c_k = RotY(theta_k)^T C - d`` by least squares.

    Returns the solution ``(C, d_x, d_z)``, each frame's distance (mm) from its
    place on the circle, and which frames the fit used: it is refitted without
    the frames more than 4x the median (and 1 mm) off (up to twice), as one
    frame turned upside down, or with a wrong angle, pulls a plain fit off
    every frame's centre. Fewer than half the frames (or 3) left: the plain fit.
    """
    A = np.zeros((3 * len(Ts), 5))
    b = np.zeros(3 * len(Ts))
    for k, (T, th) in enumerate(zip(Ts, theta, strict=True)):
        A[3 * k:3 * k + 3, :3] = rot_y(th).T
        A[3 * k, 3] = -1.0
        A[3 * k + 2, 4] = -1.0
        b[3 * k:3 * k + 3] = camera_centre_table(T)
    rows = np.ones(len(Ts), bool)
    for _ in range(3):
        sol, *_ = np.linalg.lstsq(A[np.repeat(rows, 3)], b[np.repeat(rows, 3)], rcond=None)
        per_frame = np.linalg.norm((A @ sol - b).reshape(-1, 3), axis=1)
        keep = per_frame <= max(4.0 * float(np.median(per_frame[rows])), 1.0)
        if keep.sum() < max(3, len(Ts) // 2) or np.array_equal(keep, rows):
            break
        rows = keep
    return sol, per_frame, rows


def _init_turntable(Ts: list[np.ndarray], theta: np.ndarray, yaw_known: bool) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray, float]:
    """``R_cam_axis, t_cam_axis, d_xz`` from single-view poses and angles; and the camera centres' median
    distance (mm) from the fitted circle (robust to a few bad frames).

    With consistent yaws (marks) the camera centres in the table frame obey the
    linear model ``c_k = RotY(theta_k)^T C - d`` (C: camera centre in the axis frame).
    """
    if yaw_known:
        M = sum(T[:3, :3] @ rot_y(th).T for T, th in zip(Ts, theta, strict=True))
        R_ca = project_rotation(M)
        sol, per_frame, _ = circle_fit(Ts, theta)
        C, d = sol[:3], sol[3:]
        return R_ca, -R_ca @ C, d, float(np.median(per_frame))
    n = np.mean([T[:3, 1] for T in Ts], axis=0)
    R_ca = rotation_from_normal(n, x_hint_cam=Ts[0][:3, 0])
    return R_ca, np.mean([T[:3, 3] for T in Ts], axis=0), np.zeros(2), float("nan")


def _mark_weights(stds_deg: Sequence[float], noise_px: float) -> np.ndarray:
    s = np.radians(np.maximum(np.asarray(stds_deg, float), 0.005))
    return np.where(np.isfinite(s), max(noise_px, 0.05) / s, 0.0)


# --------------------------------------------------------------------------- the models
@dataclass(frozen=True)
class FitSetup:
    """What every fit of one sequence shares: frame names, the step (None: the marks), the starting
    state, the intrinsics always free (``base``), whether the stroke is, and the progress report."""

    names: list[str]
    step_deg: float | None
    state0: FitState
    base: tuple[str, ...]
    free_stroke: bool
    report: FitReport | None = None


def fit_turntable(singles, idx: list[int], setup: FitSetup, theta0: np.ndarray, free_theta: np.ndarray,
                  yaw_known: bool, noise_px: float) -> tuple[JointFit, float]:
    """The turntable model on frames ``idx`` from angles ``theta0`` (rad; ``free_theta`` marks those
    fitted), and the camera centres' median distance (mm) off the initial circle."""
    frames = [singles[k].edges for k in idx]
    Ts = [singles[k].T for k in idx]
    R_ca, t_ca, d, centre_rms = _init_turntable(Ts, theta0, yaw_known)
    st = replace(setup.state0, R_cam_axis=R_ca, t_cam_axis=t_ca, d_xz=d, theta=theta0.copy(), R=None, t=None)
    mark_R = [singles[k].T[:3, :3] if singles[k].yaw_ok else None for k in idx]
    mark_w = _mark_weights([singles[k].angle_std_deg if singles[k].yaw_ok else np.nan for k in idx], noise_px)
    fit = fit_joint(frames, st, "turntable", setup.base, setup.free_stroke, report=setup.report,
                    free_theta=free_theta, free_yaw=yaw_known, mark_R=mark_R, mark_w=mark_w)
    return fit, centre_rms


def fit_handheld(singles, idx: list[int], setup: FitSetup) -> JointFit:
    """The hand-held model on frames ``idx``, from their single-view poses."""
    frames = [singles[k].edges for k in idx]
    st = replace(setup.state0, R=[singles[k].T[:3, :3] for k in idx], t=[singles[k].T[:3, 3] for k in idx],
                 R_cam_axis=None, t_cam_axis=None, d_xz=None, theta=None)
    return fit_joint(frames, st, "handheld", setup.base, setup.free_stroke, report=setup.report)


def _refit(fit: JointFit, free_intr: tuple[str, ...], state: FitState | None = None, report: FitReport | None = None,
           stage: str = "") -> JointFit:
    p = fit.problem
    problem = JointProblem(p.frames, fit.state if state is None else state, free_intr, p.free_stroke, p.model,
                           free_theta=p.free_theta, free_yaw=p.free_yaw, mark_R=p.mark_R, mark_w=p.mark_w)
    return solve_joint(problem, robust=False, report=report, stage=stage)


def extend_intrinsics(fit: JointFit, base: tuple[str, ...], extra: tuple[str, ...], notes: dict,
                      report: FitReport | None = None) -> JointFit:
    """Free ``extra`` intrinsics too, keeping those the data constrain (std <= MAX_STD).

    The least constrained one (largest std / MAX_STD) is dropped and the rest
    refitted until all pass: freeing k2 can make k1 look unconstrained only
    because the two trade off.
    """
    left = list(extra)
    while left:
        trial = _refit(fit, base + tuple(left), report=report,
                       stage=f"{fit.problem.model} + {', '.join(left)}")
        ratio = {n: trial.std[n] / MAX_STD[n] if np.isfinite(trial.std[n]) else np.inf for n in left}
        worst = max(left, key=lambda n: ratio[n])
        if ratio[worst] <= 1.0:
            return trial
        notes[worst] = (f"not estimated: unconstrained by these views (1 sigma {trial.std[worst]:.3g} > "
                        f"{MAX_STD[worst]:g}); kept at {'the image centre' if worst in ('cx', 'cy') else '0'}")
        left.remove(worst)
    return fit


def add_distortion(fit: JointFit, notes: dict, report: FitReport | None = None) -> JointFit:
    """Free k1, then k2, each kept only if constrained (``MAX_STD``) and worth it.

    Worth it: the RMS edge residual drops by ``MIN_RMS_GAIN``. A small
    systematic edge bias (blur, ink spread varying with the ring's image size)
    is otherwise absorbed by a "significant" k1 of a few 1e-3 that trades
    against f: on a rendered 36-frame turntable without distortion k1 came out
    +0.0027 +- 0.0003 and moved f by 0.06 % without lowering the RMS; a real
    k1 = -0.1 lowers it by ~20 % at 0.15 px noise.
    """
    cur = fit.problem.free_intr
    for k in ("k1", "k2"):
        trial = extend_intrinsics(fit, cur, (k,), notes, report)
        if k not in trial.problem.free_intr:
            if k == "k1":
                notes["k2"] = "not estimated: k1 is not"
            return fit
        if trial.rms_px > (1.0 - MIN_RMS_GAIN) * fit.rms_px:
            notes[k] = (f"not estimated: it would lower the RMS only from {fit.rms_px:.4f} to "
                        f"{trial.rms_px:.4f} px (less than {100 * MIN_RMS_GAIN:.0f} %)")
            if k == "k1":
                notes["k2"] = "not estimated: k1 is not"
            return fit
        fit, cur = trial, cur + (k,)
    return fit


def choose_mode(mode, singles, ok, angled, fit_tt, centre_off, distance):
    """'turntable' or 'handheld', and why (medians over frames: a few bad frames do not decide)."""
    if mode != "auto":
        return mode, f"--mode {mode}"
    if len(ok) < 3:
        return "handheld", f"only {len(ok)} calibrated frame(s): no turntable model"
    if len(angled) < 3:
        return "handheld", "turntable angles unknown (angle marks unreadable, no step given)"
    if np.isfinite(centre_off) and centre_off > MODE_CENTRE_TOL * distance:
        return "handheld", (f"camera centres do not lie on one circle about an axis "
                            f"(median {centre_off:.1f} mm off at {distance:.0f} mm)")
    if fit_tt is None:
        return "handheld", "turntable fit failed"
    single = float(np.median([singles[k].rms_px for k in angled]))
    joint = float(np.median(fit_tt.rms_per_frame))
    if joint > MODE_RMS_RATIO * single + 0.05:
        return "handheld", f"turntable model's median frame RMS {joint:.3f} px vs single views' {single:.3f} px"
    return "turntable", (f"fixed camera: turntable model's median frame RMS {joint:.3f} px vs single views' "
                         f"{single:.3f} px, camera centres on one circle (median {centre_off:.2f} mm off)")


def bad_frames(fit: JointFit, used: list[int]) -> dict[int, str]:
    """Frames whose edge RMS under the shared model exceeds ``BAD_FRAME_RATIO`` x the median (and 1 px)."""
    r = fit.rms_per_frame
    med = float(np.median(r))
    lim = max(BAD_FRAME_RATIO * med, BAD_FRAME_MIN_PX)
    return {used[i]: f"does not fit the shared camera: RMS {r[i]:.2f} px (median {med:.2f} px)"
            for i in np.flatnonzero(r > lim)}


# --------------------------------------------------------------------------- the angle marks, read again
def reread_marks(fit: JointFit, used: list[int], reader: AngleReader, report: FitReport | None = None) -> JointFit:
    """Read the marks again through the joint model's camera and poses, and refit.

    The first reading went through each frame's single-view ``f`` and normal;
    the joint ones are better, and so is the rectified mark track.
    """
    p, st = fit.problem, fit.state
    Ts = st.poses()
    mark_R, w = list(p.mark_R), p.mark_w.copy()
    for i, k in enumerate(used):
        if mark_R[i] is None:
            continue
        try:
            T, std = reader(k, st.K, Ts[i], st.dist)
        except FRAME_ERRORS:
            continue  # keep the first reading
        mark_R[i] = np.asarray(T, float)[:3, :3]
        w[i] = _mark_weights([std], fit.rms_px)[0]
    prob = JointProblem(p.frames, st, p.free_intr, p.free_stroke, p.model, free_theta=p.free_theta,
                        free_yaw=p.free_yaw, mark_R=mark_R, mark_w=w)
    return solve_joint(prob, robust=False, report=report, stage="turntable, marks read again")


def reread_yaw(fit: JointFit, used: list[int], singles, reader: AngleReader) -> None:
    """Handheld: set each frame's rotation about the normal from the marks read through the final camera.

    The rings do not see it, so the fit kept the single-view reading, taken
    through that frame's own f and without the distortion.
    """
    st = fit.state
    assert st.R is not None and st.t is not None  # handheld
    for i, k in enumerate(used):
        if not singles[k].yaw_ok:
            continue
        try:
            T, _ = reader(k, st.K, make_T(st.R[i], st.t[i]), st.dist)
        except FRAME_ERRORS:
            continue
        st.R[i] = np.asarray(T, float)[:3, :3]
