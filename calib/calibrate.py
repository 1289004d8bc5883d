"""Single-view calibration from two concentric rings: the public entry point.

``calibrate_view(obs, spec)`` fits a conic to every edge point set, checks that
the rings are concentric and have the nominal radius ratio, solves focal length
and table pose in closed form (``pencil`` or the paper's method) and, by
default, refines them by maximum likelihood over all edge points (``refine``).

Observability. With the principal point known, the focal length follows from
how far the vanishing line of the table lies from the principal point; when the
table is nearly parallel to the image plane that line runs off to infinity and
``f`` becomes unobservable (exactly so at 0°, whatever the viewing ray: an
off-centre target on a plane parallel to the sensor images to exact circles for
every ``f``). The tilt checked is therefore the angle between the table normal
and the OPTICAL AXIS (not the ray to the centre): in the noise study
(``benchmarks/calib_noise.py --tilt-study``, σ = 0.5 px, f = 3000 px, 360 points
per ring) the 1σ of ``f`` is ~11–15 % at 4°, ~6.5 % at 6°, ~4 % at 8°,
~1.8 % at 20°; an off-centre target at 2° from the axis but 6.6° from its ray
still gave 31 % median error. Views under ``MIN_TILT_DEG`` = 8° are refused.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from .camera import angle_between_deg
from .conics import conic_to_ellipse, sampson_distance
from .refine import edge_residuals, refine_view
from .solve_paper import solve_paper
from .solve_pencil import concentric_conics, fit_edge_conics, solve_pencil
from .target import TargetSpec
from .types import CalibrationError, CalibrationStd, Intrinsics, TargetObservation, ViewCalibration, image_centre

__all__ = ["SOLVERS", "MIN_TILT_DEG", "calibrate_view", "tilt_deg"]

SOLVERS = ("paper", "pencil", "refine")
MIN_TILT_DEG = 8.0
# Model check: the ML residual RMS may exceed the free-ellipse RMS by this
# factor plus floor. Measured (paper view, 200 points/ring): concentric rings
# give a ratio <= 1.00 at 0.1–2 px noise; an inner ring 1 mm off-centre gives
# 2.2–2.4 at 0.5 px, 10–11 at 0.1 px; 2 mm gives 4 at 0.5 px.
ADEQUACY_FACTOR = 2.0
ADEQUACY_FLOOR_PX = 0.25


def tilt_deg(T_cam_table: np.ndarray) -> float:
    """Angle (degrees) between the table normal and the camera's optical axis."""
    n = np.asarray(T_cam_table, dtype=np.float64)[:3, 1]
    return angle_between_deg(-n, np.array([0.0, 0.0, 1.0]))


def _refuse_tilt(tilt: float) -> CalibrationError:
    return CalibrationError(
        f"view too close to fronto-parallel: tilt {tilt:.1f}° (need ≥ ~{MIN_TILT_DEG:.0f}°); "
        "tilt the camera further towards the table plane"
    )


def _ellipse_tilt_deg(C: np.ndarray) -> float:
    """Rough tilt without ``f``: ``acos(minor / major)`` of a ring ellipse."""
    e = conic_to_ellipse(C)
    return float(np.degrees(np.arccos(np.clip(e.b / e.a, 0.0, 1.0))))


def calibrate_view(
    obs: TargetObservation,
    spec: TargetSpec,
    *,
    solver: str = "refine",
    principal_point_px=None,
    focal_guess_px: float | None = None,
) -> ViewCalibration:
    """Focal length and table pose from one view of the two-ring target.

    Parameters
    ----------
    obs : TargetObservation
        Edge points of the rings (``calib.rings.detect_rings``), pixels.
    spec : TargetSpec
        Nominal target: the stroke width is used for ``side = +-1`` edges
        (``refine`` estimates it); ring radii are taken from ``obs.edges``.
    solver : {"refine", "pencil", "paper"}
        ``paper``: the paper as written (cross-ratio centre, eq. 17–27);
        ``pencil``: closed form from the conic pencil and the circular points;
        ``refine`` (default): maximum likelihood over the edge points,
        initialised by ``pencil`` (``paper`` if that fails). The ML fit is run
        for every solver as the concentric-circles model check.
    principal_point_px : (2,) float, optional
        Default: the image centre ``((W-1)/2, (H-1)/2)``.
    focal_guess_px : float, optional
        Used only when the closed-form focal length fails (``refine`` then
        starts from the pose solved with this focal length).

    Returns
    -------
    ViewCalibration
        ``std`` holds 1σ from ``refine`` (NaN for the closed-form solvers);
        ``rms_px`` is the RMS edge residual at the result.

    Raises
    ------
    CalibrationError
        Fewer than two rings, wrong radius ratio, edges that two concentric
        circles do not explain (``ADEQUACY_FACTOR``), a view closer to
        fronto-parallel than ``MIN_TILT_DEG``, or no solution.
    ValueError
        Unknown solver.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    pp = (image_centre(obs.width, obs.height) if principal_point_px is None
          else cast(tuple[float, float], tuple(map(float, principal_point_px))))
    if len(obs.radii_mm()) < 2:
        raise CalibrationError(f"need two concentric rings, found {len(obs.radii_mm())}")
    has_stroke = any(e.side != 0 for e in obs.edges)
    stroke = float(spec.stroke_mm) if has_stroke else 0.0
    fits = fit_edge_conics(obs.edges)
    cc = concentric_conics(fits, stroke)
    f, T = _closed_form(obs, cc, stroke, pp, solver, focal_guess_px)
    tilt = tilt_deg(T)
    if tilt < MIN_TILT_DEG:
        raise _refuse_tilt(tilt)
    # The ML fit also tests the model: two concentric circles on one plane must
    # explain the edges about as well as free ellipses do.
    r = refine_view(obs.edges, Intrinsics.from_focal(f, obs.width, obs.height, pp).K, T, stroke)
    free_rms = _free_ellipse_rms(fits)
    if r.rms_px > ADEQUACY_FACTOR * free_rms + ADEQUACY_FLOOR_PX:
        raise CalibrationError(
            f"edges do not fit two concentric circles on one plane: RMS {r.rms_px:.2f} px against "
            f"{free_rms:.2f} px for free ellipses (rings not concentric, lens distortion or wrong edges)"
        )
    if solver == "refine":
        if tilt_deg(r.T_cam_table) < MIN_TILT_DEG:
            raise _refuse_tilt(tilt_deg(r.T_cam_table))
        return ViewCalibration(
            intrinsics=Intrinsics.from_focal(r.focal_px, obs.width, obs.height, pp),
            T_cam_table=r.T_cam_table, std=r.std, rms_px=r.rms_px, solver=solver, stroke_mm=r.stroke_mm,
        )
    K = Intrinsics.from_focal(f, obs.width, obs.height, pp)
    e = edge_residuals(K.K, T, stroke, obs.edges)
    std = CalibrationStd(focal_px=float("nan"), normal_deg=float("nan"), t_mm=np.full(3, np.nan))
    return ViewCalibration(intrinsics=K, T_cam_table=T, std=std, rms_px=float(np.sqrt(np.mean(e**2))),
                           solver=solver, stroke_mm=stroke)


def _free_ellipse_rms(fits) -> float:
    """RMS Sampson distance (px) of the edge sets from their own fitted conics."""
    ss, dof = 0.0, 0
    for C, e in fits:
        d = sampson_distance(C, e.uv_px)
        ss += float(d @ d)
        dof += max(len(d) - 5, 1)
    return float(np.sqrt(ss / dof))


def _closed_form(obs, cc, stroke, pp, solver, focal_guess_px):
    """``(f, T_cam_table)`` from the requested closed form (refine: pencil, then paper)."""
    order = {"paper": ("paper",), "pencil": ("pencil",), "refine": ("pencil", "paper")}[solver]
    errors = []
    for name in order:
        try:
            if name == "pencil":
                return solve_pencil(cc, pp)
            return solve_paper(cc, obs.edges, stroke, pp)
        except CalibrationError as exc:
            errors.append(exc)
    outer = cc.centre_line[max(cc.centre_line)]
    rough_tilt = _ellipse_tilt_deg(outer)
    if rough_tilt < MIN_TILT_DEG:
        raise _refuse_tilt(rough_tilt) from errors[-1]
    if focal_guess_px is not None and solver == "refine":
        return solve_pencil(cc, pp, focal_px=float(focal_guess_px))
    if len(errors) == 1:
        raise errors[0]
    raise CalibrationError("; ".join(f"{n}: {e}" for n, e in zip(order, errors, strict=True))) from errors[-1]
