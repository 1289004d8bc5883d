"""Closed-form calibration from the pencil of two concentric image conics.

Geometry
--------
A circle of radius ``r`` about the table origin images to the conic
``C(r) ~ A - r^2 B`` with ``A = H^{-T} diag(1, 1, 0) H^{-1}`` (positive
semi-definite, rank 2: the pair of isotropic lines through the projected centre)
and ``B = H^{-T} diag(0, 0, 1) H^{-1} = l l^T`` (``l``: the vanishing line of the
table plane). All concentric circles therefore lie in ONE pencil, and two of
them, ``C_a = s_a (A - r_a^2 B)`` and ``C_b = s_b (A - r_b^2 B)``, give
``det(C_a - lambda C_b) = 0`` with a double root ``lambda = s_a / s_b``
(member ``~ l l^T``) and a distinct root ``lambda = s_a r_a^2 / (s_b r_b^2)``
whose member ``~ A`` has the projected centre ``c`` as its null vector. The
vanishing line is the polar of the centre, ``l ~ C c``.

The images of the circular points ``I, J`` are the intersections of any member
with ``l``; they lie on the image of the absolute conic
``omega = K^{-T} K^{-1} ~ diag(1, 1, f^2)`` (coordinates relative to the
principal point), so ``I_1^2 + I_2^2 + f^2 I_3^2 = 0`` gives ``f^2`` (least
squares over its real and imaginary parts). Then the plane normal is
``n ~ K^T l`` and the depth of the centre follows from the known radius: the
viewing cone ``Q = K^T C K`` of a circle of radius ``R`` centred at
``t = s d`` (``d = K^{-1} c``) is
``Q ~ s^2 [(n.d)^2 I - (n.d)(n d^T + d n^T) + |d|^2 n n^T] - R^2 n n^T``,
linear in ``(s^2, R^2)`` up to scale. Every step is exact on exact conics.

Edge data (both edges of a printed stroke, radii ``R +- w/2``) is turned into
centre-line conics inside the same pencil: each fitted conic is scaled to
``C_j / s_j = A - r_j^2 B`` (``s_j`` from ``A_j = C_j + mu_j l l^T``, which has
``c`` as null vector), and the centre line is the member of radius ``R``:
``A - R^2 B = mean_j(C_j / s_j + (r_j^2 - R^2) B)``. For a ring seen on both
sides this is the interpolation in ``r^2``; its dependence on the nominal
width is second order (``w^2 / 4`` in ``r^2``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import make_T, rotation_from_normal
from .conics import conic_to_ellipse, fit_conic, normalize_conic
from .types import CalibrationError, EdgePoints

__all__ = [
    "ConcentricConics",
    "fit_edge_conics",
    "concentric_conics",
    "circular_points",
    "focal_from_circular_points",
    "pose_from_centre_and_normal",
    "solve_pencil",
    "centred_frame",
]

# A ring's two measured radii must match the nominal ratio within this
# (relative, on the radius ratio). Measured scatter: <= 1.1 % at 2 px noise
# (paper view, 200 points per ring), so 3 % refuses e.g. 50/30 labelled 50/28.
RADIUS_RATIO_TOL = 0.03
# Poles of the vanishing line w.r.t. the further edge conics must agree within
# this fraction of the outer ellipse's size (+1 px) for them to be concentric.
CONCENTRIC_TOL = 0.02


@dataclass(frozen=True)
class ConcentricConics:
    """The pencil of the imaged concentric circles, in pixels.

    Attributes
    ----------
    centre_px : (2,) float64
        Image of the circles' centre (not the ellipse centre), pixels.
    vanishing_line : (3,) float64
        Vanishing line of the table plane, ``l^T x = 0`` for pixels
        ``x = (u, v, 1)``; unit norm.
    A : (3, 3) float64
        Member ``A`` of the pencil (radius 0), scaled so that every circle of
        radius ``r`` (mm) images to ``A - r^2 * beta * l l^T``.
    beta : float
        Scale of the ``l l^T`` member (see ``A``).
    centre_line : dict[float, (3, 3) ndarray]
        Normalised centre-line conic per ring radius (mm), outer first.
    radius_ratio : float
        Measured outer/inner radius ratio (from the conics alone).
    """

    centre_px: np.ndarray
    vanishing_line: np.ndarray
    A: np.ndarray
    beta: float
    centre_line: dict
    radius_ratio: float

    def conic(self, radius_mm: float) -> np.ndarray:
        """Image conic of the table circle of ``radius_mm`` implied by the pencil."""
        l = self.vanishing_line
        return normalize_conic(self.A - radius_mm**2 * self.beta * np.outer(l, l))


def centred_frame(principal_point_px, scale_px: float) -> np.ndarray:
    """Pixel -> centred, scaled coordinates ``x_n = S x``: ``((u - cx)/s, (v - cy)/s, 1)``.

    Conics map as ``C_n = S^{-T} C S^{-1}``, lines as ``l_n = S^{-T} l``.
    """
    cx, cy = principal_point_px
    s = float(scale_px)
    return np.array([[1 / s, 0, -cx / s], [0, 1 / s, -cy / s], [0, 0, 1.0]])


def fit_edge_conics(edges: tuple[EdgePoints, ...]) -> list[tuple[np.ndarray, EdgePoints]]:
    """Direct least-squares conic of every edge point set (``calib.conics.fit_conic``).

    Raises ``CalibrationError`` when a set does not determine an ellipse.
    """
    out = []
    for e in edges:
        try:
            out.append((fit_conic(e.uv_px), e))
        except ValueError as exc:
            raise CalibrationError(f"edge of the {e.ring_radius_mm:g} mm ring: {exc}") from exc
    return out


def _distinct_eigen(Ca: np.ndarray, Cb: np.ndarray) -> float:
    """The simple root of ``det(Ca - lambda Cb) = 0``; the other two (nearly) coincide.

    With noise the double root splits into two close real roots or a complex
    pair; the simple root is the one whose two companions are closest.
    """
    lam = np.linalg.eigvals(np.linalg.solve(Cb, Ca))
    gaps = []
    for k in range(3):
        a, b = np.delete(lam, k)
        gaps.append(abs(a - b) / max(abs(a) + abs(b), 1e-300))
    return float(np.real(lam[int(np.argmin(gaps))]))


def _centre_and_vanishing_line(Ca: np.ndarray, Cb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projected centre ``c`` (3,), ``c_3 = 1``, and unit vanishing line ``l`` of a concentric pair."""
    lam = _distinct_eigen(Ca, Cb)
    _, _, Vt = np.linalg.svd(Ca - lam * Cb)
    c = Vt[-1] / Vt[-1][2]
    l = Ca @ c
    return c, l / np.linalg.norm(l)


def _scaled_members(conics, c, l) -> tuple[list[np.ndarray], np.ndarray]:
    """Per conic ``A_j = (C_j + mu_j l l^T) / s_j`` (null vector ``c``) and ``rho_j = mu_j / s_j``.

    Then ``C_j / s_j = A_j - rho_j l l^T`` with ``rho_j = beta r_j^2``.
    """
    lc = float(l @ c)
    A_list, rho = [], []
    for C in conics:
        mu = -float(c @ C @ c) / lc**2
        Aj = C + mu * np.outer(l, l)
        s = np.linalg.norm(Aj) * np.sign(np.trace(Aj))
        A_list.append(Aj / s)
        rho.append(mu / s)
    return A_list, np.array(rho)


def concentric_conics(
    fits: list[tuple[np.ndarray, EdgePoints]], stroke_mm: float
) -> ConcentricConics:
    """Pencil geometry of edge conics: centre, vanishing line, centre-line conics.

    Parameters
    ----------
    fits : list of ((3, 3) conic in pixels, EdgePoints)
        One fitted conic per edge set; ``EdgePoints.radius_mm(stroke_mm)`` gives
        its radius on the table.
    stroke_mm : float
        Nominal stroke width, used for the radii of ``side = +-1`` edges.

    Raises
    ------
    CalibrationError
        Fewer than two rings, conics that are not concentric, or a measured
        radius ratio that disagrees with the nominal one.
    """
    rings = sorted({e.ring_radius_mm for _, e in fits}, reverse=True)
    if len(rings) < 2:
        raise CalibrationError(f"need two concentric rings, found {len(rings)}")
    conics = [normalize_conic(C) for C, _ in fits]
    radii = np.array([e.radius_mm(stroke_mm) for _, e in fits])
    if np.any(radii <= 0):
        raise ValueError(f"stroke {stroke_mm} mm gives a non-positive edge radius")
    # Centre and vanishing line from the two most different radii first; with
    # stroke edges, again from the centre-line conics, in which a constant
    # pixel offset of the detected edges (blur, threshold) cancels to first order.
    ia, ib = int(np.argmax(radii)), int(np.argmin(radii))
    Ca, Cb = conics[ia], conics[ib]
    for _ in range(2 if any(e.side != 0 for _, e in fits) else 1):
        c, l = _centre_and_vanishing_line(Ca, Cb)
        A_list, rho = _scaled_members(conics, c, l)
        beta = float(rho @ radii**2 / (radii**2 @ radii**2))
        ll = np.outer(l, l)
        centre_line = {}
        for R in rings:
            idx = [j for j, (_, e) in enumerate(fits) if e.ring_radius_mm == R]
            members = [A_list[j] - (rho[j] - (radii[j] ** 2 - R**2) * beta) * ll for j in idx]
            centre_line[R] = normalize_conic(np.mean(members, axis=0))
        Ca, Cb = centre_line[rings[0]], centre_line[rings[-1]]
    _check_concentric(conics, l, c)
    A = np.mean(A_list, axis=0)
    ratio = _measured_ratio(rings, fits, rho, radii)
    nominal = rings[0] / rings[1]
    if abs(ratio / nominal - 1.0) > RADIUS_RATIO_TOL:
        raise CalibrationError(
            f"ring radius ratio does not match the target: measured {ratio:.3f}, "
            f"nominal {nominal:.3f} ({rings[0]:g}/{rings[1]:g} mm); check --r-outer/--r-inner"
        )
    return ConcentricConics(
        centre_px=c[:2].copy(), vanishing_line=l, A=A, beta=beta,
        centre_line=centre_line, radius_ratio=ratio,
    )


def _measured_ratio(rings, fits, rho, radii) -> float:
    """Outer/inner centre-line radius ratio measured from the conic scales.

    ``rho_j = beta r_j^2`` with ``beta`` unknown; per ring the centre-line
    ``R^2`` is ``mean(rho_j) * R^2 / mean(r_j^2)`` (nominal edge radii ``r_j``:
    for a two-sided stroke the width enters only as ``w^2/4``), so the ratio of
    two rings is free of ``beta``.
    """
    r2 = []
    for R in rings[:2]:
        idx = [j for j, (_, e) in enumerate(fits) if e.ring_radius_mm == R]
        r2.append(np.mean(rho[idx]) * R**2 / np.mean(radii[idx] ** 2))
    return float(np.sqrt(r2[0] / r2[1]))


def _check_concentric(conics, l, c) -> None:
    """Raise unless the pole of ``l`` w.r.t. every conic is the centre ``c``.

    For the two conics that define ``c`` and ``l`` this holds by construction
    (any two conics share a self-polar triangle), so it tests only the other
    edge conics; ``calib.calibrate`` tests the whole model by its residuals.
    """
    try:
        size = max(conic_to_ellipse(C).a for C in conics)
    except ValueError as exc:
        raise CalibrationError(f"edge conic is not an ellipse: {exc}") from exc
    for C in conics:
        p = np.linalg.solve(C, l)
        if abs(p[2]) < 1e-12 * np.linalg.norm(p):
            raise CalibrationError("rings are not concentric (vanishing line through an ellipse)")
        d = np.linalg.norm(p[:2] / p[2] - c[:2])
        if d > CONCENTRIC_TOL * size + 1.0:
            raise CalibrationError(
                f"rings are not concentric: their centres disagree by {d:.1f} px"
            )


def circular_points(C_n: np.ndarray, l_n: np.ndarray) -> np.ndarray:
    """Image of the circular point ``I`` (3,) complex: ``C_n`` meets ``l_n``.

    ``C_n``, ``l_n`` in centred, scaled coordinates (:func:`centred_frame`).
    ``J`` is the complex conjugate. Raises ``CalibrationError`` when the line
    meets the conic in real points (the vanishing line crosses an ellipse).
    """
    _, _, Vt = np.linalg.svd(l_n.reshape(1, 3))
    p, q = Vt[1], Vt[2]  # span of the line's points
    a, b, c = q @ C_n @ q, p @ C_n @ q, p @ C_n @ p
    disc = a * c - b * b
    if disc <= 0 or a == 0:
        raise CalibrationError("vanishing line meets the ring ellipses: not a view of a plane circle")
    t = (-b + 1j * np.sqrt(disc)) / a
    return p + t * q


def focal_from_circular_points(I: np.ndarray) -> float:
    """``f^2`` from ``I^T diag(1, 1, f^2) I = 0`` (least squares over re/im).

    Returns ``f^2`` in the units of the coordinates of ``I`` (may be <= 0 on bad
    data; the caller decides).
    """
    a = I[0] ** 2 + I[1] ** 2
    b = I[2] ** 2
    return float(-np.real(a * np.conj(b)) / abs(b) ** 2)


def pose_from_centre_and_normal(
    conics_n: dict, centre_n: np.ndarray, normal_cam: np.ndarray, f_n: float
) -> np.ndarray:
    """Circle centre in the camera frame (3,), mm, from its image and the normal.

    Parameters
    ----------
    conics_n : dict[float, (3, 3) ndarray]
        Image conic per circle radius (mm), centred scaled coordinates.
    centre_n : (2,) float64
        Image of the circle centre, centred scaled coordinates.
    normal_cam : (3,) float64
        Unit plane normal, camera frame.
    f_n : float
        Focal length in the scaled units.

    Notes
    -----
    With ``t = s d`` (``d = K^{-1} c``, ``d_3 = 1``) and any in-plane axes
    ``r1, r3``, the plane homography is ``H = G diag(1, 1, s)`` with
    ``G = K [r1 r3 d]``, so ``G^T C G ~ diag(1, 1, -R^2 / s^2)`` and
    ``s^2 = -R^2 (M_11 + M_22) / (2 M_33)``, ``M = G^T C G``. (A least-squares
    fit of the 3x3 viewing cone instead was ~40x noisier in depth.) The rings'
    depths are averaged with weights ``R^2``.
    """
    K_n = np.diag([f_n, f_n, 1.0])
    R = rotation_from_normal(normal_cam)
    d = np.array([centre_n[0] / f_n, centre_n[1] / f_n, 1.0])
    G = K_n @ np.column_stack([R[:, 0], R[:, 2], d])
    depths, weights = [], []
    for radius, C in conics_n.items():
        M = G.T @ C @ G
        s2 = -(M[0, 0] + M[1, 1]) / (2.0 * M[2, 2])
        if not np.isfinite(s2) or s2 <= 0:
            raise CalibrationError("no circle depth fits the ring conics (inconsistent conics)")
        depths.append(radius * np.sqrt(s2))
        weights.append(radius**2)
    return float(np.average(depths, weights=weights)) * d


def solve_pencil(
    cc: ConcentricConics,
    principal_point_px,
    *,
    focal_px: float | None = None,
    scale_px: float = 1000.0,
) -> tuple[float, np.ndarray]:
    """Focal length and ``T_cam_table`` in closed form from the conic pencil.

    Parameters
    ----------
    cc : ConcentricConics
        From :func:`concentric_conics`.
    principal_point_px : (2,) float
        Principal point, pixels.
    focal_px : float, optional
        Known focal length (pixels); when given the circular-point step is
        skipped and only the pose is solved.
    scale_px : float
        Coordinate scale used internally for conditioning (no effect on the result).

    Returns
    -------
    focal_px : float
    T_cam_table : (4, 4) float64
        Column 1 of the rotation is the plane normal towards the camera.

    Raises
    ------
    CalibrationError
        When the circular points give no real focal length.
    """
    S = centred_frame(principal_point_px, scale_px)
    Si = np.linalg.inv(S)
    l_n = Si.T @ cc.vanishing_line
    conics_n = {R: normalize_conic(Si.T @ C @ Si) for R, C in cc.centre_line.items()}
    R_outer = max(conics_n)
    if focal_px is None:
        f2 = focal_from_circular_points(circular_points(conics_n[R_outer], l_n))
        if not np.isfinite(f2) or f2 <= 0:
            raise CalibrationError("focal length unobservable from the circular points (f^2 <= 0)")
        f_n = np.sqrt(f2)
    else:
        f_n = float(focal_px) / scale_px
    n = np.array([f_n * l_n[0], f_n * l_n[1], l_n[2]])
    n /= np.linalg.norm(n)
    centre_n = (S @ np.append(cc.centre_px, 1.0))[:2]
    ray = np.array([centre_n[0] / f_n, centre_n[1] / f_n, 1.0])
    if n @ ray > 0:  # normal towards the camera: camera centre at table Y > 0
        n = -n
    t = pose_from_centre_and_normal(conics_n, centre_n, n, f_n)
    return float(f_n * scale_px), make_T(rotation_from_normal(n), t)
