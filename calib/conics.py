"""Conics in pixel coordinates: fitting, ellipse parameters, distances.

A conic is a symmetric 3x3 matrix ``C`` with ``x^T C x = 0`` for homogeneous
image points ``x = (u, v, 1)``; equivalently the paper's eq. (12)
``A u^2 + B u v + C v^2 + D u + E v + F = 0`` with
``C = [[A, B/2, D/2], [B/2, C, E/2], [D/2, E/2, F]]``.

Fitting is the ellipse-specific direct least squares of Fitzgibbon et al. in
the numerically stable form of Halir & Flusser, on Hartley-normalised points
(centroid at the origin, mean distance sqrt(2)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import as_points

__all__ = [
    "Ellipse",
    "fit_conic",
    "normalize_conic",
    "conic_from_coeffs",
    "conic_coeffs",
    "conic_to_ellipse",
    "ellipse_to_conic",
    "conic_center",
    "sampson_distance",
    "algebraic_residual",
    "ellipse_points",
    "is_ellipse",
]


@dataclass(frozen=True)
class Ellipse:
    """Geometric ellipse parameters in pixels.

    ``center_px`` (2,), semi-axes ``a >= b`` (pixels), ``angle_rad`` of the
    major axis from the +u axis towards +v.
    """

    center_px: np.ndarray
    a: float
    b: float
    angle_rad: float


def conic_from_coeffs(coeffs) -> np.ndarray:
    """3x3 conic from ``(A, B, C, D, E, F)`` of eq. (12)."""
    A, B, C, D, E, F = np.asarray(coeffs, dtype=np.float64)
    return np.array([[A, B / 2, D / 2], [B / 2, C, E / 2], [D / 2, E / 2, F]])


def conic_coeffs(C: np.ndarray) -> np.ndarray:
    """``(A, B, C, D, E, F)`` of eq. (12) from a 3x3 conic."""
    return np.array([C[0, 0], 2 * C[0, 1], C[1, 1], 2 * C[0, 2], 2 * C[1, 2], C[2, 2]])


def normalize_conic(C: np.ndarray) -> np.ndarray:
    """Unit Frobenius norm, sign such that the ellipse interior is negative."""
    C = 0.5 * (np.asarray(C, dtype=np.float64) + np.asarray(C, dtype=np.float64).T)
    C = C / np.linalg.norm(C)
    # For an ellipse the upper-left 2x2 block is definite; make it positive so
    # that points inside evaluate negative.
    if np.trace(C[:2, :2]) < 0:
        C = -C
    return C


def is_ellipse(C: np.ndarray) -> bool:
    """True for a real, non-degenerate ellipse."""
    C = normalize_conic(C)
    if np.linalg.det(C[:2, :2]) <= 0:
        return False
    centre = conic_center(C)
    x = np.append(centre, 1.0)
    return bool(x @ C @ x < 0)


def _hartley(uv: np.ndarray) -> np.ndarray:
    m = uv.mean(axis=0)
    d = np.sqrt(((uv - m) ** 2).sum(axis=1)).mean()
    s = np.sqrt(2.0) / max(d, 1e-12)
    return np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1.0]])


def fit_conic(uv_px: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Ellipse-specific direct least-squares conic through ``uv_px`` (N >= 5, 2).

    Returns the normalised 3x3 conic (see :func:`normalize_conic`). Raises
    ``ValueError`` when the points do not determine an ellipse, or when
    ``uv_px`` is not (N, 2) (OpenCV's (N, 1, 2) is accepted) or ``weights``
    not (N,).
    """
    uv = as_points(uv_px, 2, "uv_px")
    if len(uv) < 5:
        raise ValueError(f"need at least 5 points to fit a conic, got {len(uv)}")
    T = _hartley(uv)
    x = uv[:, 0] * T[0, 0] + T[0, 2]
    y = uv[:, 1] * T[1, 1] + T[1, 2]
    D1 = np.column_stack([x * x, x * y, y * y])
    D2 = np.column_stack([x, y, np.ones_like(x)])
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(uv),):
            raise ValueError(f"weights must be ({len(uv)},) like uv_px, got {w.shape}")
        w = np.sqrt(w)[:, None]
        D1, D2 = D1 * w, D2 * w
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        Tm = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError as exc:
        raise ValueError("degenerate point set for conic fit") from exc
    M = S1 + S2 @ Tm
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])
    w_, V = np.linalg.eig(M)
    V = np.real(V)
    cond = 4 * V[0] * V[2] - V[1] ** 2
    ok = np.flatnonzero(cond > 0)
    if len(ok) == 0:
        raise ValueError("points do not determine an ellipse")
    a1 = V[:, ok[np.argmin(np.abs(np.real(w_[ok])))]]
    coeffs = np.concatenate([a1, Tm @ a1])
    Cn = conic_from_coeffs(coeffs)
    return normalize_conic(T.T @ Cn @ T)


def conic_center(C: np.ndarray) -> np.ndarray:
    """Centre (2,) of a central conic, pixels."""
    return np.linalg.solve(C[:2, :2], -C[:2, 2])


def conic_to_ellipse(C: np.ndarray) -> Ellipse:
    """Geometric parameters of an ellipse conic; ``ValueError`` if not an ellipse."""
    C = normalize_conic(C)
    if not is_ellipse(C):
        raise ValueError("conic is not a real ellipse")
    c = conic_center(C)
    x = np.append(c, 1.0)
    k = -(x @ C @ x)  # > 0
    evals, evecs = np.linalg.eigh(C[:2, :2] / k)  # ascending: smallest -> major axis
    a, b = 1.0 / np.sqrt(evals[0]), 1.0 / np.sqrt(evals[1])
    major = evecs[:, 0]
    angle = float(np.arctan2(major[1], major[0]))
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2
    return Ellipse(center_px=c, a=float(a), b=float(b), angle_rad=angle)


def ellipse_to_conic(e: Ellipse) -> np.ndarray:
    """Normalised conic of an :class:`Ellipse`."""
    ca, sa = np.cos(e.angle_rad), np.sin(e.angle_rad)
    R = np.array([[ca, -sa], [sa, ca]])
    A2 = R @ np.diag([1 / e.a**2, 1 / e.b**2]) @ R.T
    c = np.asarray(e.center_px, float)
    C = np.zeros((3, 3))
    C[:2, :2] = A2
    C[:2, 2] = C[2, :2] = -A2 @ c
    C[2, 2] = c @ A2 @ c - 1.0
    return normalize_conic(C)


def algebraic_residual(C: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """``x^T C x`` for each point (N,)."""
    uv = as_points(uv_px, 2, "uv_px")
    x = np.column_stack([uv, np.ones(len(uv))])
    return np.einsum("ij,jk,ik->i", x, C, x)


def sampson_distance(C: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """Signed first-order geometric distance (pixels) of points to the conic (N,).

    ``x^T C x / (2 |(C x)_{1:2}|)``; negative inside for a normalised ellipse.
    """
    uv = as_points(uv_px, 2, "uv_px")
    x = np.column_stack([uv, np.ones(len(uv))])
    Cx = x @ C.T
    num = np.einsum("ij,ij->i", x, Cx)
    grad = 2.0 * np.linalg.norm(Cx[:, :2], axis=1)
    return num / np.maximum(grad, 1e-300)


def ellipse_points(e: Ellipse, n: int = 360) -> np.ndarray:
    """``n`` points (N, 2) on an ellipse, evenly spaced in its parameter."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ca, sa = np.cos(e.angle_rad), np.sin(e.angle_rad)
    x, y = e.a * np.cos(t), e.b * np.sin(t)
    return np.column_stack([e.center_px[0] + ca * x - sa * y, e.center_px[1] + sa * x + ca * y])
