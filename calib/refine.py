"""Maximum-likelihood single-view refinement over all edge points.

Residual
--------
Each edge point ``(u, v)`` is back-projected onto the table plane: with the ray
``q = (u - cx, v - cy, f)``, the plane ``n . X = n . t`` (normal ``n``, circle
centre ``t``, camera frame) is met at ``X = s q``, ``s = (n.t)/(n.q)``; its
distance from the centre in the plane is ``rho = |X - t|`` (mm). The residual
is the first-order geometric distance in pixels from the projected edge circle
of radius ``r = R + side * w / 2``::

    e = (rho - r) / |grad_uv rho|

which is the Sampson distance of the radial function ``rho`` (``rho^2 - r^2``
is the projected conic ``x^T C x`` up to a positive factor). Edges of a
printed stroke carry two widths: ``w`` (mm, on the paper: ink spread) and a
constant pixel offset ``delta`` of the detected edges (blur and threshold pull
both edges of a dark stroke inwards by the same number of pixels, which no
width in mm reproduces under perspective); the residual of a stroke edge is
``e + side * delta``. With ``delta`` fixed at 0 a 0.3 px detector offset biased
``f`` by 0.13 % on the paper's view; with it free the bias vanished and the
rendered frames of ``turntable synth`` gave the printed 3.0 mm stroke (2.97)
instead of 2.85. Measured against
the exact point-to-ellipse distance on the paper's view (tests/test_solvers.py):
max error 0.005 / 0.020 px at 1 / 2 px off the outer ellipse (curvature radius
down to 31 px), 0.008 / 0.034 px on the inner one (17 px) -- about 1.6x
smaller than the Sampson distance of the conic itself (0.008 / 0.031 and
0.014 / 0.057 px), and far below the noise it weighs, so no exact
(quartic) distance is needed.

Jacobian (analytic; the weight ``1 / |grad rho|`` is frozen per evaluation, so
the neglected term is proportional to the residual and vanishes at a perfect
fit), with ``D = X - t``, ``D^ = D / rho``, ``k = (D^ . q) / (n . q)``::

    d rho / d t  = k n - D^
    d rho / d n  = -k D            (tangent to the unit sphere: D . n = 0)
    d rho / d f  = s (D^_3 - k n_3)
    d rho / d cx = -s (D^_1 - k n_1),   d rho / d cy = -s (D^_2 - k n_2)
    d e / d w    = -side / 2 / |grad rho|,  d e / d delta = side

:func:`edge_residuals` and :func:`edge_linearisation` depend on ``K``,
``T_cam_table`` and the stroke only, so a multi-view joint refinement (shared
``K``, one pose per frame) can stack them; :func:`refine_view` adds the
single-view parameter packing ``[f, a1, a2, t (3), w, delta]`` with the normal
``n = N(n0 + a1 e1 + a2 e2)`` (``e1, e2`` an orthonormal tangent basis at ``n0``),
solved by :func:`calib.lm.levenberg_marquardt` on the dense normal equations
(:class:`calib.lm.DenseSystem`), the tangent origin re-based at every accepted step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .camera import make_T, rotation_from_normal
from .lm import DenseSystem, dense_covariance, levenberg_marquardt
from .types import CalibrationError, CalibrationStd, EdgePoints

__all__ = [
    "EdgeLinearisation",
    "RefineResult",
    "edge_residuals",
    "edge_linearisation",
    "edge_geometry",
    "EdgeGeometry",
    "stack_edges",
    "refine_view",
]

ROBUST_SCALE_PX = 1.0  # soft_l1 scale of the robust stage
INLIER_SIGMAS = 4.0  # final L2 stage keeps |e| < max(4 robust sigma, INLIER_FLOOR_PX)
INLIER_FLOOR_PX = 0.5
DEFAULT_MAX_POINTS = 2000
LM_LAMBDA0 = 1e-6  # initial Levenberg-Marquardt damping (see _solve)


@dataclass(frozen=True)
class EdgeLinearisation:
    """Residuals and their derivatives at one camera/pose/stroke.

    All arrays have N rows, one per edge point (edges concatenated in order).

    Attributes
    ----------
    residual_px : (N,) signed distance from the projected edge circle, pixels
        (positive outside).
    d_focal : (N,) px per px of focal length.
    d_principal : (N, 2) px per px of ``(cx, cy)``.
    d_normal : (N, 3) px per unit of the plane normal (camera frame); tangent
        to the unit sphere at the current normal.
    d_t : (N, 3) px per mm of the circle centre ``t_cam_table``.
    d_stroke : (N,) px per mm of stroke width.
    d_offset : (N,) px per px of edge offset ``delta`` (= side).
    """

    residual_px: np.ndarray
    d_focal: np.ndarray
    d_principal: np.ndarray
    d_normal: np.ndarray
    d_t: np.ndarray
    d_stroke: np.ndarray
    d_offset: np.ndarray


def stack_edges(edges: tuple[EdgePoints, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate edge sets: ``uv_px`` (N, 2), ring radius (N,) mm, side (N,)."""
    if len(edges) == 0:
        raise ValueError("no edge points")
    uv = np.concatenate([e.uv_px for e in edges])
    R = np.concatenate([np.full(len(e.uv_px), float(e.ring_radius_mm)) for e in edges])
    side = np.concatenate([np.full(len(e.uv_px), float(e.side)) for e in edges])
    return uv, R, side


class EdgeGeometry(NamedTuple):
    """Back-projection terms of :func:`edge_geometry` (module docstring's notation), N points.

    ``s`` (N,) ray scale to the plane; ``D`` (N, 3) mm, ``X - t``; ``rho`` (N,) mm, ``|D|``;
    ``Dh`` (N, 3) ``D / rho``; ``k`` (N,) ``(D^ . q) / (n . q)``; ``grad`` (N, 2) mm/px,
    ``d rho / d (u, v)``; ``g`` (N,) mm/px, ``|grad|``.
    """

    s: np.ndarray
    D: np.ndarray
    rho: np.ndarray
    Dh: np.ndarray
    k: np.ndarray
    grad: np.ndarray
    g: np.ndarray


def edge_geometry(f, cx, cy, n, t, uv) -> EdgeGeometry:
    """Back-projection terms shared by residual and Jacobian (:class:`EdgeGeometry`).

    ``f, cx, cy``: pixels; ``uv`` (N, 2) pixels; ``n``, ``t``: the plane normal and
    circle centre (camera frame, mm), (3,) for all points or (N, 3), one per point
    (many views' points at once).
    """
    q = np.empty((len(uv), 3))
    q[:, 0] = uv[:, 0] - cx
    q[:, 1] = uv[:, 1] - cy
    q[:, 2] = f
    if n.ndim == 1:
        nq = q @ n
        s = (n @ t) / nq
    else:
        nq = np.einsum("ij,ij->i", q, n)
        s = np.einsum("ij,ij->i", n, t) / nq
    D = s[:, None] * q - t
    rho = np.sqrt(np.einsum("ij,ij->i", D, D))
    Dh = D / rho[:, None]
    k = np.einsum("ij,ij->i", Dh, q) / nq
    grad = s[:, None] * (Dh[:, :2] - k[:, None] * n[..., :2])  # d rho / d (u, v), mm per px
    g = np.sqrt(np.einsum("ij,ij->i", grad, grad))
    return EdgeGeometry(s, D, rho, Dh, k, grad, g)


def _unpack_K(K):
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K: expected (3, 3), got {K.shape}")
    return K[0, 0], K[0, 2], K[1, 2]


def edge_residuals(
    K: np.ndarray, T_cam_table: np.ndarray, stroke_mm: float, edges: tuple[EdgePoints, ...],
    edge_offset_px: float = 0.0,
) -> np.ndarray:
    """Signed pixel distance of every edge point from its projected edge circle.

    Parameters
    ----------
    K : (3, 3) float64
        Camera matrix (square pixels, zero skew), pixels.
    T_cam_table : (4, 4) float64
        Table (mm) to camera (mm); only the normal (column 1) and ``t`` matter.
    stroke_mm : float
        Stroke width w; edge radius is ``ring_radius_mm + side * w / 2``.
    edges : tuple of EdgePoints
    edge_offset_px : float
        Detected stroke edges sit this many pixels inside the stroke's true
        edges (blur/threshold); 0 for centre-line points.

    Returns
    -------
    (N,) float64
        Residuals in pixels, edges concatenated in order.
    """
    uv, R, side = stack_edges(edges)
    f, cx, cy = _unpack_K(K)
    T = np.asarray(T_cam_table, dtype=np.float64)
    geo = edge_geometry(f, cx, cy, T[:3, 1], T[:3, 3], uv)
    rho, g = geo.rho, geo.g
    return (rho - (R + 0.5 * side * stroke_mm)) / g + side * edge_offset_px


def edge_linearisation(
    K: np.ndarray, T_cam_table: np.ndarray, stroke_mm: float, edges: tuple[EdgePoints, ...],
    edge_offset_px: float = 0.0,
) -> EdgeLinearisation:
    """Residuals and analytic derivatives (see the module docstring)."""
    uv, R, side = stack_edges(edges)
    f, cx, cy = _unpack_K(K)
    T = np.asarray(T_cam_table, dtype=np.float64)
    return _linearise(f, cx, cy, T[:3, 1], T[:3, 3], stroke_mm, uv, R, side, delta=edge_offset_px)


def _linearise(f, cx, cy, n, t, w, uv, R, side, inv_g=None, delta=0.0) -> EdgeLinearisation:
    s, D, rho, Dh, k, grad, g = edge_geometry(f, cx, cy, n, t, uv)
    if inv_g is None:
        inv_g = 1.0 / g
    e = (rho - (R + 0.5 * side * w)) * inv_g + side * delta
    d_t = (k[:, None] * n - Dh) * inv_g[:, None]
    d_n = -(k * inv_g)[:, None] * D
    d_f = s * (Dh[:, 2] - k * n[2]) * inv_g
    d_pp = -grad * inv_g[:, None]
    d_w = -0.5 * side * inv_g
    return EdgeLinearisation(e, d_f, d_pp, d_n, d_t, d_w, side.astype(np.float64))


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane perpendicular to unit ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(n, e1)])


@dataclass(frozen=True)
class RefineResult:
    """Output of :func:`refine_view`.

    Attributes
    ----------
    focal_px : float
    T_cam_table : (4, 4) float64
    stroke_mm : float
        Estimated stroke (or the fixed value when not fitted).
    edge_offset_px : float
        Estimated inward offset of the detected stroke edges (0 when the
        stroke is not fitted).
    edge_offset_std_px : float
        Its 1-sigma (NaN when not fitted).
    std : CalibrationStd
        1-sigma from ``s^2 (J^T J)^{-1}`` at the final L2 solution.
    rms_px : float
        RMS residual of the points kept by the final stage.
    n_points : int
        Points used (after subsampling and outlier rejection).
    """

    focal_px: float
    T_cam_table: np.ndarray
    stroke_mm: float
    edge_offset_px: float
    edge_offset_std_px: float
    std: CalibrationStd
    rms_px: float
    n_points: int


def subsample_edges(edges: tuple[EdgePoints, ...], max_points: int) -> tuple[EdgePoints, ...]:
    """Every k-th point of each edge set so that at most ``max_points`` remain."""
    total = sum(len(e.uv_px) for e in edges)
    step = int(np.ceil(total / max(int(max_points), 1)))
    if step <= 1:
        return tuple(edges)
    return tuple(EdgePoints(e.uv_px[::step], e.ring_radius_mm, e.side) for e in edges)


def _stroke_observable(edges) -> bool:
    """True when some ring has points on both edges of its stroke."""
    sides: dict[float, set[int]] = {}
    for e in edges:
        sides.setdefault(e.ring_radius_mm, set()).add(e.side)
    return any({-1, 1} <= s for s in sides.values())


class _Problem:
    """Single-view parameter packing ``p = [f, a1, a2, tx, ty, tz(, w, delta)]``.

    The normal is ``n = N(n0 + a1 e1 + a2 e2)``; the solver re-bases ``n0`` to
    the current normal after every accepted step, so ``a = 0`` at every
    linearisation and ``dn/da = [e1 e2]`` exactly.
    """

    def __init__(self, uv, R, side, cx, cy, n0, w_fixed, fit_w):
        self.uv, self.R, self.side = uv, R, side
        self.cx, self.cy = cx, cy
        self.fit_w, self.w_fixed = fit_w, w_fixed
        self.rebase(n0)
        self.inv_g = None

    def freeze_weights(self, p):
        """Fix the pixel weights ``1 / |grad rho|`` at ``p`` (None: current)."""
        f, n, t, _, _ = self.unpack(p)
        self.inv_g = 1.0 / edge_geometry(f, self.cx, self.cy, n, t, self.uv).g

    def rebase(self, n0):
        self.n0 = n0 / np.linalg.norm(n0)
        self.E = _tangent_basis(self.n0)

    def unpack(self, p):
        """``(f, unit normal, t, w, delta)``."""
        m = self.n0 + self.E @ p[1:3]
        w, delta = (p[6], p[7]) if self.fit_w else (self.w_fixed, 0.0)
        return p[0], m / np.linalg.norm(m), p[3:6], w, delta

    def rebased(self, p):
        """Same parameters with the normal's tangent origin moved to ``n(p)``."""
        _, n, _, _, _ = self.unpack(p)
        self.rebase(n)
        q = p.copy()
        q[1:3] = 0.0
        return q

    def lin(self, p) -> EdgeLinearisation:
        f, n, t, w, delta = self.unpack(p)
        return _linearise(f, self.cx, self.cy, n, t, w, self.uv, self.R, self.side, self.inv_g, delta)

    def residual(self, p) -> np.ndarray:
        f, n, t, w, delta = self.unpack(p)
        geo = edge_geometry(f, self.cx, self.cy, n, t, self.uv)
        rho, g = geo.rho, geo.g
        inv_g = 1.0 / g if self.inv_g is None else self.inv_g
        return (rho - (self.R + 0.5 * self.side * w)) * inv_g + self.side * delta

    def jac(self, L: EdgeLinearisation) -> np.ndarray:
        """Jacobian (N, p) at a linearisation taken with ``a = 0``."""
        cols = [L.d_focal[:, None], L.d_normal @ self.E, L.d_t]
        if self.fit_w:
            cols += [L.d_stroke[:, None], L.d_offset[:, None]]
        return np.hstack(cols)


class _Scaled:
    """:class:`calib.lm.LeastSquaresProblem` of a :class:`_Problem` in scaled parameters ``x = p / scale``.

    ``scale`` (p,) gives every column of the Jacobian a comparable size, so the
    normal equations are well conditioned; ``accept`` re-bases the normal.
    """

    def __init__(self, prob: _Problem, scale: np.ndarray):
        self.prob, self.scale = prob, scale

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return self.prob.residual(x * self.scale)

    def normal_equations(self, x: np.ndarray, r: np.ndarray, weights: np.ndarray) -> DenseSystem:
        L = self.prob.lin(x * self.scale)
        return DenseSystem.from_jacobian(self.prob.jac(L) * self.scale, L.residual_px, weights)

    def accept(self, x: np.ndarray) -> np.ndarray:
        return self.prob.rebased(x * self.scale) / self.scale


def _solve(prob: _Problem, p: np.ndarray, scale: np.ndarray, loss_scale: float | None,
           rtol: float = 1e-9) -> np.ndarray:
    """:func:`calib.lm.levenberg_marquardt` on the single view from ``p``; the solution in ``p``'s units.

    The damping starts at ``LM_LAMBDA0``, near Gauss-Newton: ``p`` is the closed-form solution (or the
    previous stage's), where full Gauss-Newton steps are taken (from 1e-3 the final stage took 4 steps
    instead of 2 on the paper's view, and refine_view 1.3x the time).
    """
    fit = levenberg_marquardt(_Scaled(prob, scale), p / scale, loss_scale=loss_scale, rtol=rtol, max_iter=30,
                              lam0=LM_LAMBDA0)
    return fit.x * scale


def refine_view(
    edges: tuple[EdgePoints, ...],
    K0: np.ndarray,
    T0_cam_table: np.ndarray,
    stroke_mm: float,
    *,
    fit_stroke: bool | None = None,
    max_points: int = DEFAULT_MAX_POINTS,
) -> RefineResult:
    """Refine focal length, plane normal, circle centre (and stroke, edge offset) over edge points.

    Robust stage (``soft_l1`` at ``ROBUST_SCALE_PX``), then points beyond
    ``max(4 sigma_MAD, 0.5 px)`` are dropped and a pure-L2 stage gives the
    estimate and its covariance ``s^2 (J^T J)^{-1}``, ``s^2 = sum e^2 / (N - p)``.

    Parameters
    ----------
    edges : tuple of EdgePoints
    K0 : (3, 3) float64
        Initial camera matrix; its principal point stays fixed.
    T0_cam_table : (4, 4) float64
        Initial pose (from ``solve_pencil`` / ``solve_paper``).
    stroke_mm : float
        Initial (nominal) stroke width, mm; kept when not fitted.
    fit_stroke : bool, optional
        Estimate the stroke width and the edge offset; default: when some ring
        has both edges.
    max_points : int
        Edge sets are subsampled evenly to at most this many points.

    Raises
    ------
    CalibrationError
        When the fit leaves the valid region or too few points agree.
    """
    fit_w = _stroke_observable(edges) if fit_stroke is None else bool(fit_stroke)
    used = subsample_edges(edges, max_points)
    uv, R, side = stack_edges(used)
    f0, cx, cy = _unpack_K(K0)
    T0 = np.asarray(T0_cam_table, dtype=np.float64)
    prob = _Problem(uv, R, side, cx, cy, T0[:3, 1], float(stroke_mm), fit_w)
    p = np.concatenate([[f0, 0.0, 0.0], T0[:3, 3], [stroke_mm, 0.0] if fit_w else []])
    tn = np.linalg.norm(T0[:3, 3])
    scale = np.concatenate([[0.01 * f0, 0.01, 0.01], np.full(3, 0.01 * tn), [0.1, 0.1] if fit_w else []])
    prob.freeze_weights(p)
    p = _solve(prob, p, scale, ROBUST_SCALE_PX, rtol=1e-5)  # the L2 stage polishes
    prob.inv_g = None
    e = prob.residual(p)
    sigma = 1.4826 * np.median(np.abs(e))
    keep = np.abs(e) < max(INLIER_SIGMAS * sigma, INLIER_FLOOR_PX)
    if keep.sum() < len(p) + 5:
        raise CalibrationError("too few edge points agree with any ring projection")
    prob = _Problem(uv[keep], R[keep], side[keep], cx, cy, prob.n0, float(stroke_mm), fit_w)
    for _ in range(2):  # weights frozen per pass: cost and gradient agree exactly
        prob.freeze_weights(p)
        p = _solve(prob, p, scale, None)
    prob.inv_g = None
    L = prob.lin(p)
    if not np.all(np.isfinite(L.residual_px)):
        raise CalibrationError("refinement diverged (edge rays miss the table plane)")
    return _result(prob, p, L.residual_px, prob.jac(L))


def _result(prob: _Problem, p, e, J) -> RefineResult:
    """Estimate and 1-sigma from ``s^2 (J^T J)^{-1}`` (:func:`calib.lm.dense_covariance`; ``J`` taken at
    ``a = 0``)."""
    s2 = float(np.sum(e * e)) / max(len(e) - len(p), 1)
    cov = dense_covariance(J, s2)
    sd = np.sqrt(np.abs(np.diag(cov)))
    f, n, t, w, delta = prob.unpack(p)
    if n @ t > 0:
        raise CalibrationError("refinement turned the table plane away from the camera")
    std = CalibrationStd(
        focal_px=float(sd[0]),
        normal_deg=float(np.degrees(np.sqrt(abs(cov[1, 1] + cov[2, 2])))),
        t_mm=sd[3:6].copy(),
        stroke_mm=float(sd[6]) if prob.fit_w else float("nan"),
    )
    return RefineResult(
        focal_px=float(f), T_cam_table=make_T(rotation_from_normal(n), t), stroke_mm=float(w),
        edge_offset_px=float(delta), edge_offset_std_px=float(sd[7]) if prob.fit_w else float("nan"),
        std=std, rms_px=float(np.sqrt(np.mean(e**2))), n_points=len(e),
    )
