"""The paper's solver, as written: cross-ratio centre, normal, then f and Tz.

Implements "Direct camera calibration using two concentric circles from a
single view" (§3–4) in coordinates relative to the principal point
``(u', v') = (u - u0, v - v0)`` (scaled by a constant for conditioning only):

1. Conics of the two rings by normalised direct least squares
   (``calib.conics.fit_conic``, eq. 12). For edge data (both edges of a stroke
   of nominal width w) the centre-line conics are taken from the pencil of the
   edge conics (interpolation in ``r^2``; see ``calib.solve_pencil``); the
   paper itself fits thin circles.
2. Projected circle centre ``Pc`` (eq. 13–16): it lies on the line through the
   two ellipse centres; that line meets the outer ellipse in ``P1, P4'`` and
   the inner one in ``P2, P4``. With signed positions along the line and
   ``P1`` (outer), ``P2`` (inner) on the same side, ``P4`` (inner) on the
   other, ``Cr(P1, P2; Pc, P4) = (P1Pc * P2P4) / (P1P4 * P2Pc)`` equals
   ``Cr3D = 2 R1 / (R1 + R2)`` (eq. 15), which is linear in ``Pc``. The paper
   does not say which side is ``P1``; both choices are exact, and we average the
   two (a symmetric estimate under noise).
3. Normal (eq. 17–21): ``n ~ Q (Xc, Yc, f)`` with ``Q`` the principal ellipse's
   cone, i.e. ``n ~ (alpha1, alpha2, alpha3 / f)``; sign flipped to our
   convention (towards the camera; the paper's §5.1 normal points away).
4. ``Tx = Xc Tz / f``, ``Ty = Yc Tz / f`` (eq. 22).
5. ``f`` and ``Tz`` from the over-determined linear system (eq. 23–27) over the
   points of the principal ellipse. The coefficients of eq. 23 are derived in
   ``calib/PAPER_EQ23.md`` and built by :func:`eq23_conics`.

Exact on exact data (tests/test_solvers.py).
"""

from __future__ import annotations

import numpy as np

from .camera import make_T, rotation_from_normal
from .conics import conic_center, normalize_conic
from .solve_pencil import ConcentricConics, centred_frame
from .types import CalibrationError, EdgePoints

__all__ = ["projected_centre_cross_ratio", "eq23_conics", "solve_paper"]


def _line_conic_params(C: np.ndarray, p0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Sorted real parameters ``t`` where ``p0 + t d`` (2-vectors) meets conic ``C``."""
    P, D = np.append(p0, 1.0), np.append(d, 0.0)
    a, b, c = D @ C @ D, P @ C @ D, P @ C @ P
    disc = b * b - a * c
    if disc <= 0 or a == 0:
        raise CalibrationError("line through the ellipse centres misses an ellipse")
    r = np.sqrt(disc)
    return np.sort([(-b - r) / a, (-b + r) / a])


def projected_centre_cross_ratio(
    C_outer: np.ndarray, C_inner: np.ndarray, r_outer: float, r_inner: float
) -> np.ndarray:
    """Image of the common centre of two concentric circles (eq. 13–16).

    Parameters
    ----------
    C_outer, C_inner : (3, 3) float64
        Image conics of the circles of radius ``r_outer`` > ``r_inner`` (any
        pixel frame).

    Returns
    -------
    (2,) float64
        The projected centre in the conics' frame.
    """
    e_o, e_i = conic_center(C_outer), conic_center(C_inner)
    d = e_i - e_o
    if np.linalg.norm(d) < 1e-9 * (1 + np.linalg.norm(e_o)):
        # Ellipse centres coincide (e.g. fronto-parallel): that is the centre.
        return 0.5 * (e_o + e_i)
    d = d / np.linalg.norm(d)
    to = _line_conic_params(C_outer, e_o, d)
    ti = _line_conic_params(C_inner, e_o, d)
    k = 2.0 * r_outer / (r_outer + r_inner)  # eq. (15)
    estimates = []
    for p1, p2, p4 in ((to[1], ti[1], ti[0]), (to[0], ti[0], ti[1])):
        # (p1 - pc)(p2 - p4) = k (p1 - p4)(p2 - pc), linear in pc
        pc = (k * (p1 - p4) * p2 - p1 * (p2 - p4)) / (k * (p1 - p4) - (p2 - p4))
        estimates.append(pc)
    return e_o + np.mean(estimates) * d


def eq23_conics(C_n: np.ndarray, centre_n: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficient conics of eq. (23): ``C ~ f^2 M1 + (f^2/Tz^2) M2 + M3``.

    Parameters
    ----------
    C_n : (3, 3) float64
        Principal ellipse in coordinates relative to the principal point
        (eq. 12 coefficients ``A..F``).
    centre_n : (2,) float64
        Projected circle centre ``(Xc, Yc)`` in the same coordinates.
    radius : float
        Radius of the circle the conic is to describe (mm); any circle
        concentric with the principal one on the same plane.

    Returns
    -------
    M1, M2, M3 : (3, 3) float64
        ``(Ac_k, Bc_k, ..., Fc_k) = conic_coeffs(Mk)`` of eq. (23). With
        ``alpha`` of eq. (21), ``k = alpha . (Xc, Yc, 1)`` and the linear form
        ``g(u, v) = alpha . (u, v, 1)``:
        ``M1 = (alpha - k e3)(alpha - k e3)^T``, ``M2 = -R^2 alpha alpha^T``,
        ``M3 = (k e1 - Xc alpha)(...)^T + (k e2 - Yc alpha)(...)^T``
        (derivation: ``calib/PAPER_EQ23.md``).
    """
    A, B2, D2 = C_n[0]
    _, C, E2 = C_n[1]
    F = C_n[2, 2]
    Xc, Yc = centre_n
    alpha = np.array([A * Xc + B2 * Yc + D2, B2 * Xc + C * Yc + E2, D2 * Xc + E2 * Yc + F])  # eq. (21)
    k = alpha @ np.array([Xc, Yc, 1.0])
    e1, e2, e3 = np.eye(3)
    l1 = alpha - k * e3
    lu, lv = k * e1 - Xc * alpha, k * e2 - Yc * alpha
    return np.outer(l1, l1), -radius**2 * np.outer(alpha, alpha), np.outer(lu, lu) + np.outer(lv, lv)


def solve_paper(
    cc: ConcentricConics,
    edges: tuple[EdgePoints, ...],
    stroke_mm: float,
    principal_point_px,
    *,
    scale_px: float = 1000.0,
) -> tuple[float, np.ndarray]:
    """Focal length and ``T_cam_table`` by the paper's method (eq. 13–27).

    Parameters
    ----------
    cc : ConcentricConics
        Only its centre-line conics are used (fitted conics for side-0 data).
    edges : tuple of EdgePoints
        The points of the principal (outer) ring enter eq. (25), each with its
        edge radius ``ring_radius_mm + side * stroke_mm / 2``.
    stroke_mm : float
        Nominal stroke width, mm.
    principal_point_px : (2,) float
    scale_px : float
        Constant coordinate scale for conditioning (no effect on the result).

    Returns
    -------
    focal_px : float
    T_cam_table : (4, 4) float64

    Raises
    ------
    CalibrationError
        When eq. (27) gives no positive ``f^2`` and ``f^2/Tz^2``.
    """
    S = centred_frame(principal_point_px, scale_px)
    Si = np.linalg.inv(S)
    radii = sorted(cc.centre_line, reverse=True)
    R1, R2 = radii[0], radii[1]
    C1 = normalize_conic(Si.T @ cc.centre_line[R1] @ Si)
    C2 = normalize_conic(Si.T @ cc.centre_line[R2] @ Si)
    centre = projected_centre_cross_ratio(C1, C2, R1, R2)
    rows, rhs = [], []
    for e in edges:
        if e.ring_radius_mm != R1:
            continue
        M1, M2, M3 = eq23_conics(C1, centre, e.radius_mm(stroke_mm))
        x = np.column_stack([(e.uv_px - np.asarray(principal_point_px)) / scale_px, np.ones(len(e.uv_px))])
        def q(M, x=x):
            return np.einsum("ij,jk,ik->i", x, M, x)

        rows.append(np.column_stack([q(M1), q(M2)]))
        rhs.append(-q(M3))
    W, b = np.vstack(rows), np.concatenate(rhs)
    X, *_ = np.linalg.lstsq(W, b, rcond=None)  # eq. (27)
    if not (X[0] > 0 and X[1] > 0):
        raise CalibrationError("the paper's linear system (eq. 25) has no positive f^2, f^2/Tz^2")
    f_n = np.sqrt(X[0])
    Tz = f_n / np.sqrt(X[1])
    A, B2, D2 = C1[0]
    _, Cc, E2 = C1[1]
    F = C1[2, 2]
    Xc, Yc = centre
    alpha = np.array([A * Xc + B2 * Yc + D2, B2 * Xc + Cc * Yc + E2, D2 * Xc + E2 * Yc + F])
    n = np.array([alpha[0], alpha[1], alpha[2] / f_n])  # eq. (19)-(20)
    n /= np.linalg.norm(n)
    t = np.array([Xc * Tz / f_n, Yc * Tz / f_n, Tz])  # eq. (22)
    if n @ t > 0:  # our convention: normal towards the camera
        n = -n
    return float(f_n * scale_px), make_T(rotation_from_normal(n), t)
