"""Pinhole projection of the table plane and its circles; pose helpers.

A point ``(X, 0, Z)`` of the table plane maps to the image through the plane
homography ``H = K [r1 r3 t]`` (``r1``, ``r3`` the first and third columns of
``R_cam_table``, ``t = t_cam_table``): ``x ~ H (X, Z, 1)^T``. A circle of radius
``r`` about the table origin is the plane conic ``diag(1, 1, -r^2)`` and images
to the conic ``C = H^{-T} diag(1, 1, -r^2) H^{-1}`` (``x^T C x = 0``).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "as_K",
    "as_poses",
    "make_T",
    "look_at",
    "invert_T",
    "rotation_from_normal",
    "plane_homography",
    "circle_conic",
    "project_points",
    "values_at_points",
    "circle_points_table",
    "camera_centre_table",
    "angle_between_deg",
]


def as_K(K) -> np.ndarray:
    """``K`` as a (3, 3) float64 array; ``ValueError`` naming the shape otherwise."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K: expected (3, 3), got {K.shape}")
    return K


def as_poses(T_cam_table, n_views: int | None = None) -> np.ndarray:
    """Per-view poses as a (V, 4, 4) float64 array (V = ``n_views`` when given)."""
    T = np.asarray(T_cam_table, dtype=np.float64)
    want = "V" if n_views is None else str(n_views)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or (n_views is not None and len(T) != n_views):
        raise ValueError(f"T_cam_table: expected ({want}, 4, 4), got {T.shape}")
    return T


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 rigid transform from a rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def look_at(centre: np.ndarray, target: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """``T_cam_frame`` (4, 4) of an OpenCV camera at ``centre`` looking at ``target``.

    Both points in one frame (table or world, mm) whose +Y is up: image "up"
    (-y) follows +Y as far as the view allows, then the camera is rolled by
    ``roll_rad`` about its optical axis (clockwise in the image).
    """
    C = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - C
    z /= np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z])  # rows: camera axes in the frame's coordinates
    return make_T(R, -R @ C)


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (``T_b_a`` from ``T_a_b``)."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def rotation_from_normal(normal_cam: np.ndarray, x_hint_cam: np.ndarray | None = None) -> np.ndarray:
    """Right-handed ``R_cam_table`` whose second column is ``normal_cam``.

    The table X axis is ``x_hint_cam`` (default: camera x) projected into the
    plane; Z = X x Y. The rotation about the normal is otherwise arbitrary.
    """
    y = np.asarray(normal_cam, dtype=np.float64)
    y = y / np.linalg.norm(y)
    hint = np.array([1.0, 0.0, 0.0]) if x_hint_cam is None else np.asarray(x_hint_cam, float)
    x = hint - y * (hint @ y)
    if np.linalg.norm(x) < 1e-9:  # hint parallel to the normal
        x = np.array([0.0, 0.0, 1.0]) - y * y[2]
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    return np.column_stack([x, y, z])


def plane_homography(K: np.ndarray, T_cam_table: np.ndarray) -> np.ndarray:
    """Homography from table-plane coordinates ``(X, Z, 1)`` (mm) to pixels."""
    R, t = T_cam_table[:3, :3], T_cam_table[:3, 3]
    return np.asarray(K, float) @ np.column_stack([R[:, 0], R[:, 2], t])


def circle_conic(K: np.ndarray, T_cam_table: np.ndarray, radius_mm: float) -> np.ndarray:
    """Image conic (pixels, ``x^T C x = 0``) of the table circle of ``radius_mm``.

    Scaled to unit Frobenius norm, sign chosen so the projected centre is inside
    (``x_c^T C x_c < 0``).
    """
    Hinv = np.linalg.inv(plane_homography(K, T_cam_table))
    C = Hinv.T @ np.diag([1.0, 1.0, -float(radius_mm) ** 2]) @ Hinv
    C = 0.5 * (C + C.T)
    return C / np.linalg.norm(C)


def project_points(K: np.ndarray, T_cam_table: np.ndarray, pts_table: np.ndarray) -> np.ndarray:
    """Project ``pts_table`` (N, 3) mm into pixels ``uv_px`` (N, 2); no distortion."""
    pts = np.asarray(pts_table, dtype=np.float64).reshape(-1, 3)
    pts_cam = pts @ T_cam_table[:3, :3].T + T_cam_table[:3, 3]
    uvw = pts_cam @ np.asarray(K, float).T
    return uvw[:, :2] / uvw[:, 2:3]


def values_at_points(K: np.ndarray, T_cam_table: np.ndarray, pts_table: np.ndarray, image: np.ndarray) -> np.ndarray:
    """(N,) ``image``'s value at the pixel nearest each point of ``pts_table`` (N, 3) mm (:func:`project_points`);
    zero (False) where that pixel is off the image."""
    H, W = image.shape[:2]
    uv = np.rint(project_points(K, T_cam_table, pts_table)).astype(np.int64)
    ok = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < W) & (uv[:, 1] < H)
    out = np.zeros(len(uv), image.dtype)
    out[ok] = image[uv[ok, 1], uv[ok, 0]]
    return out


def circle_points_table(radius_mm: float, n: int = 360) -> np.ndarray:
    """``n`` points (N, 3) evenly spaced on the table circle of ``radius_mm``."""
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.column_stack([radius_mm * np.cos(th), np.zeros(n), radius_mm * np.sin(th)])


def camera_centre_table(T_cam_table: np.ndarray) -> np.ndarray:
    """Camera centre in the table frame, mm: (3,) for one pose (4, 4), (V, 3) for poses (V, 4, 4)."""
    T = np.asarray(T_cam_table, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", T[..., :3, :3], T[..., :3, 3])


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two 3-vectors."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))
