"""OpenCV lens distortion: forward model and its exact inverse, vectorised.

OpenCV's model (``k1, k2, p1, p2[, k3[, k4, k5, k6]]``) acts on normalised
image coordinates ``x = K^{-1} (u, v, 1)``, ``r^2 = x^2 + y^2``::

    g   = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    x_d = x g + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y g + p1 (r^2 + 2 y^2) + 2 p2 x y

:func:`distort_normalized` is that map; :func:`undistort_normalized` inverts it
by Newton's method with the analytic 2x2 Jacobian (quadratic convergence;
OpenCV's ``undistortPoints`` uses a fixed-point iteration with a fixed count,
which leaves ~1e-3 px errors at k1 = -0.1 in the image corners).
:func:`undistort_px` / :func:`distort_px` wrap them for pixel coordinates with a
camera matrix ``K`` (pixel (0, 0) at the centre of the top-left pixel, as in
the README; OpenCV's own functions use the same convention for points).
"""

from __future__ import annotations

import numpy as np

from .camera import as_K

__all__ = [
    "pad_dist",
    "distort_normalized",
    "undistort_normalized",
    "distort_px",
    "undistort_px",
]

_SUPPORTED = (0, 4, 5, 8)


def pad_dist(dist) -> np.ndarray:
    """Distortion coefficients padded to the 8 of the rational model.

    Parameters
    ----------
    dist : array_like, (0,), (4,), (5,) or (8,)
        OpenCV ``k1, k2, p1, p2[, k3[, k4, k5, k6]]``.

    Returns
    -------
    (8,) float64

    Raises
    ------
    ValueError
        For other lengths (the thin-prism and tilted-sensor models are not supported).
    """
    d = np.asarray(dist, dtype=np.float64).ravel()
    if d.size not in _SUPPORTED:
        raise ValueError(f"distortion: expected 0, 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), "
                         f"got {d.size}")
    out = np.zeros(8)
    out[: d.size] = d
    return out


def _check_xy(xy) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"expected points (N, 2), got {xy.shape}")
    return xy


def _distort_with_jacobian(xy: np.ndarray, d: np.ndarray, jac: bool):
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    g = a / b
    xd = x * g + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * g + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    out = np.column_stack([xd, yd])
    if not jac:
        return out, None
    da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    dg = (da * b - a * db) / (b * b)  # dg / d(r^2)
    j00 = g + 2.0 * x * x * dg + 2.0 * p1 * y + 6.0 * p2 * x
    j01 = 2.0 * x * y * dg + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = g + 2.0 * y * y * dg + 6.0 * p1 * y + 2.0 * p2 * x
    return out, (j00, j01, j11)  # symmetric: j10 == j01


def distort_normalized(xy, dist) -> np.ndarray:
    """Apply OpenCV distortion to normalised coordinates.

    Parameters
    ----------
    xy : (N, 2) float64
        Ideal (undistorted) normalised camera coordinates ``(X/Z, Y/Z)``.
    dist : array_like
        OpenCV coefficients, see :func:`pad_dist`.

    Returns
    -------
    (N, 2) float64
        Distorted normalised coordinates.
    """
    return _distort_with_jacobian(_check_xy(xy), pad_dist(dist), jac=False)[0]


def undistort_normalized(xy_d, dist, iterations: int = 20, tol: float = 1e-14) -> np.ndarray:
    """Invert :func:`distort_normalized` by Newton's method.

    Parameters
    ----------
    xy_d : (N, 2) float64
        Distorted normalised coordinates.
    dist : array_like
        OpenCV coefficients, see :func:`pad_dist`.
    iterations : int
        Most Newton steps (converges in 3-5 for ordinary lenses).
    tol : float
        Stop when every point's residual is below this (normalised units).

    Returns
    -------
    (N, 2) float64
        Undistorted normalised coordinates; points where the model is not
        invertible (beyond the lens's fold-over radius) keep their last iterate.
    """
    xy_d = _check_xy(xy_d)
    d = pad_dist(dist)
    if not np.any(d):
        return xy_d.copy()
    xy = xy_d.copy()
    for _ in range(int(iterations)):
        f, (j00, j01, j11) = _distort_with_jacobian(xy, d, jac=True)
        e = f - xy_d
        if np.max(np.abs(e), initial=0.0) < tol:
            break
        det = j00 * j11 - j01 * j01
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        xy[:, 0] -= (j11 * e[:, 0] - j01 * e[:, 1]) / det
        xy[:, 1] -= (j00 * e[:, 1] - j01 * e[:, 0]) / det
    return xy


def _in_normalized(uv_px, K, dist, fn) -> np.ndarray:
    """Apply ``fn`` (normalised coordinates, dist) to pixels ``uv_px`` and map back with the same ``K``."""
    uv = _check_xy(uv_px)
    d = pad_dist(dist)
    if not np.any(d):
        return uv.copy()
    K = as_K(K)
    fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (uv[:, 1] - cy) / fy
    x = (uv[:, 0] - cx - s * y) / fx
    out = fn(np.column_stack([x, y]), d)
    return np.column_stack([fx * out[:, 0] + s * out[:, 1] + cx, fy * out[:, 1] + cy])


def undistort_px(uv_px, K, dist) -> np.ndarray:
    """Undistorted pixel positions (same ``K``) of distorted pixels ``uv_px`` (N, 2).

    Equivalent to ``cv2.undistortPoints(uv, K, dist, P=K)`` but iterated to
    convergence. Zero skew is not assumed.
    """
    return _in_normalized(uv_px, K, dist, undistort_normalized)


def distort_px(uv_px, K, dist) -> np.ndarray:
    """Distorted pixel positions of ideal pinhole pixels ``uv_px`` (N, 2) (same ``K``)."""
    return _in_normalized(uv_px, K, dist, distort_normalized)
