"""The cameras for other tools: a COLMAP text model (with its tracks) and nerfstudio's ``transforms.json``.

Re-exported by :mod:`recon.export` (the mesh files), whose conventions hold here
too: every file in **metres** in the table frame (+Y up, right-handed), written
whole or not at all (temporary file, then ``os.replace``).

Conversions at this edge:

* **Pixels**: our pixel centres sit at integers; COLMAP and nerfstudio put the
  top-left pixel's centre at (0.5, 0.5), so ``cx, cy`` gain 0.5 there.
* **Poses**: COLMAP stores world-to-camera (``R_cam_table`` as a Hamilton
  quaternion ``qw qx qy qz`` and ``t_cam_table`` in metres), OpenCV camera
  axes; nerfstudio stores camera-to-world (``T_table_cam``) with OpenGL camera
  axes (x right, y up, z back): ``c2w = T_table_cam @ diag(1, -1, -1, 1)``.

COLMAP tracks (:func:`surface_tracks`): a 3D point ``X`` on the final mesh is
observed in view ``k`` when it is in front of the camera, its projection

    u = K d(x),   x = (X_c / Z_c, Y_c / Z_c),   X_c = R_cam_table X + t_cam_table

(``d`` the OpenCV distortion of the original photos) falls inside the photo,
the mesh face nearest ``X`` (at most ``surface_tol_mm`` away) turns towards the
camera, and the ray from the camera centre towards ``X`` first meets the mesh
no more than ``surface_tol_mm`` before ``X`` (nothing occludes it). The observation
written is ``u`` itself (in COLMAP's pixels, ``u + 0.5``): the reprojection of
the point, so COLMAP's reprojection error is 0 up to the text precision, and
each image's tracks give its depth range as COLMAP's undistorter computes it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calib.camera import camera_centre_table

from .fileio import atomic_write_bytes

__all__ = ["export_colmap", "export_nerfstudio", "ColmapTracks", "surface_tracks", "project_photo_px",
           "MAX_TRACK_POINTS", "MM_PER_M"]

MM_PER_M = 1000.0
# OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
#: At most this many 3D points with tracks in a COLMAP export (fused points beyond it are subsampled).
MAX_TRACK_POINTS = 50_000


# --- cameras ---------------------------------------------------------------------------------------


def _check_cameras(K, width, height, frames, dist):
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K: expected (3, 3), got {K.shape}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not frames:
        raise ValueError("frames: need at least one (image_name, T_cam_table)")
    out = []
    for k, (name, T) in enumerate(frames):
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"frames[{k}]: T_cam_table must be (4, 4), got {T.shape}")
        if not str(name) or any(ch.isspace() for ch in str(name)):
            raise ValueError(f"frames[{k}]: image name {name!r} must be non-empty without whitespace")
        out.append((str(name), T))
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
    if len(d) > 5:
        raise ValueError(f"dist: expected OpenCV k1, k2, p1, p2[, k3], got {len(d)} coefficients")
    d = np.concatenate([d, np.zeros(5)])[:5]
    return K, int(width), int(height), out, d


def _colmap_camera_line(K, width, height, d) -> str:
    fx, fy = K[0, 0], K[1, 1]
    cx, cy = K[0, 2] + 0.5, K[1, 2] + 0.5  # COLMAP: top-left pixel centre at (0.5, 0.5)
    if d[4] != 0:
        params = [fx, fy, cx, cy, *d, 0.0, 0.0, 0.0]  # k4..k6 of the rational model: 0
        model = "FULL_OPENCV"
    elif np.any(d != 0):
        params = [fx, fy, cx, cy, *d[:4]]
        model = "OPENCV"
    else:
        params = [fx, fy, cx, cy]
        model = "PINHOLE"
    return f"1 {model} {width} {height} " + " ".join(f"{p:.17g}" for p in params)


def export_colmap(
    K: np.ndarray,
    width: int,
    height: int,
    frames: Sequence[tuple[str, np.ndarray]],
    out_dir: str | os.PathLike,
    *,
    dist: np.ndarray | None = None,
    points_table: np.ndarray | None = None,
    colors_rgb: np.ndarray | None = None,
    tracks: ColmapTracks | None = None,
) -> dict[str, Path]:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    COLMAP's world is our table frame in metres. One shared camera: PINHOLE;
    OPENCV (``fx fy cx cy k1 k2 p1 p2``) when ``dist`` is non-zero;
    FULL_OPENCV (``... k3 k4 k5 k6``, k4..k6 = 0) when k3 is non-zero.

    Parameters
    ----------
    K : (3, 3) float
        Pixels, pixel centres at integers (converted to COLMAP's +0.5).
    width, height : int
        Image size, pixels.
    frames : sequence of (image_name, T_cam_table)
        Image name as COLMAP should see it (relative to its image folder, no
        whitespace) and the (4, 4) table (mm) -> camera (mm) pose.
    out_dir : path
        Created if missing (typically ``.../sparse/0``).
    dist : (4,) or (5,) float, optional
        OpenCV ``k1 k2 p1 p2[ k3]`` of the images named in ``frames``.
    points_table : (P, 3) float, optional
        Points (mm, table frame) written to ``points3D.txt`` with empty tracks
        (an initialisation for Gaussian splatting); not with ``tracks``.
    colors_rgb : (P, 3) uint8, optional
        Their colours (grey if omitted).
    tracks : ColmapTracks, optional
        Points with their observations in ``frames`` (one column per frame, same
        order): ``images.txt`` lists each image's POINTS2D and ``points3D.txt``
        each point's TRACK of ``(IMAGE_ID, POINT2D_IDX)``, consistently.

    Returns
    -------
    dict
        ``{"cameras": path, "images": path, "points3D": path}``.
    """
    K, width, height, frames, d = _check_cameras(K, width, height, frames, dist)
    if tracks is not None:
        if points_table is not None or colors_rgb is not None:
            raise ValueError("give points_table/colors_rgb or tracks, not both")
        if tracks.visible.shape[1] != len(frames):
            raise ValueError(f"tracks: {tracks.visible.shape[1]} views for {len(frames)} frames")
        points_table, colors_rgb = tracks.points_table, tracks.colors_rgb
    pts = _colmap_points(points_table, colors_rgb, tracks)
    n_obs = 0 if tracks is None else int(tracks.visible.sum())
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            "# Number of cameras: 1", _colmap_camera_line(K, width, height, d)]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(frames)}, mean observations per image: {n_obs / len(frames):.6g}"]
    for i, (name, T) in enumerate(frames, start=1):
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        q = np.array([qw, qx, qy, qz]) * (1.0 if qw >= 0 else -1.0)
        t_m = T[:3, 3] / MM_PER_M
        imgs.append(f"{i} " + " ".join(f"{x:.17g}" for x in (*q, *t_m)) + f" 1 {name}")
        imgs.append("" if tracks is None else _points2d_line(tracks, i - 1))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"cameras": out / "cameras.txt", "images": out / "images.txt", "points3D": out / "points3D.txt"}
    atomic_write_bytes(paths["cameras"], ("\n".join(cams) + "\n").encode())
    atomic_write_bytes(paths["images"], ("\n".join(imgs) + "\n").encode())
    atomic_write_bytes(paths["points3D"], ("\n".join(pts) + "\n").encode())
    return paths


def _points2d_line(tracks: ColmapTracks, view: int) -> str:
    """One image's POINTS2D: its observations in point order, COLMAP pixels (+0.5), 1-based point ids."""
    idx = np.flatnonzero(tracks.visible[:, view])
    uv = tracks.uv_px[idx, view] + 0.5
    return " ".join(map("{:.6f} {:.6f} {}".format, uv[:, 0].tolist(), uv[:, 1].tolist(), (idx + 1).tolist()))


def _colmap_points(points_table, colors_rgb, tracks: ColmapTracks | None) -> list[str]:
    P = np.zeros((0, 3)) if points_table is None else np.asarray(points_table, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points_table: expected (P, 3), got {P.shape}")
    C = np.full((len(P), 3), 128, np.uint8) if colors_rgb is None else np.asarray(colors_rgb, np.uint8)
    if C.shape != P.shape:
        raise ValueError(f"colors_rgb: expected {P.shape}, got {C.shape}")
    mean_track = 0.0 if tracks is None or not len(P) else float(tracks.visible.sum()) / len(P)
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(P)}, mean track length: {mean_track:.6g}"]
    P_m = P / MM_PER_M
    if tracks is None:
        track_text = [""] * len(P)
    else:
        point2d_idx = np.cumsum(tracks.visible, axis=0) - 1  # (P, V): index in each image's POINTS2D
        pts, views = np.nonzero(tracks.visible)  # observations in point order, then view order
        obs = list(map("{} {}".format, (views + 1).tolist(), point2d_idx[pts, views].tolist()))
        ends = np.cumsum(tracks.visible.sum(axis=1)).tolist()
        track_text = [" " + " ".join(obs[a:b]) for a, b in zip([0, *ends[:-1]], ends, strict=True)]
    # ERROR 0: every observation is the point's own reprojection (see the module docstring)
    lines += [f"{i} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {c[0]} {c[1]} {c[2]} 0{tr}"
              for i, (p, c, tr) in enumerate(zip(P_m.tolist(), C.tolist(), track_text, strict=True), start=1)]
    return lines


# --- COLMAP tracks ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ColmapTracks:
    """3D points and the views that see them: the 2D-3D observations of a COLMAP model.

    Attributes
    ----------
    points_table : (P, 3) float64
        mm, table frame.
    colors_rgb : (P, 3) uint8
        sRGB.
    visible : (P, V) bool
        Point ``p`` is observed in view ``v`` (views in the order of the poses given).
    uv_px : (P, V, 2) float64
        Its projection into the original photo (with its distortion), pixel
        centres at integers; NaN where not visible.
    """

    points_table: np.ndarray
    colors_rgb: np.ndarray
    visible: np.ndarray
    uv_px: np.ndarray


def project_photo_px(K: np.ndarray, dist: np.ndarray | None, T_cam_table: np.ndarray,
                     pts_table: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project table-frame points into a photo with its lens distortion.

    Parameters
    ----------
    K : (3, 3) float
        Pixels, pixel centres at integers.
    dist : (n,) float or None
        OpenCV ``k1 k2 p1 p2[ k3 ...]``.
    T_cam_table : (4, 4) float
        Table (mm) -> camera (mm).
    pts_table : (P, 3) float
        mm.

    Returns
    -------
    uv_px : (P, 2) float64
        Distorted pixel positions (meaningless where ``z_mm <= 0``).
    ideal_px : (P, 2) float64
        The same without distortion (pinhole).
    z_mm : (P,) float64
        Depth along the optical axis.
    """
    from calib.distortion import distort_normalized

    X = np.asarray(pts_table, np.float64) @ T_cam_table[:3, :3].T + T_cam_table[:3, 3]
    z = X[:, 2]
    xy = X[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
    xy_d = xy if dist is None or not np.any(dist) else distort_normalized(xy, dist)
    K = np.asarray(K, np.float64)

    def to_px(n):
        return np.column_stack([K[0, 0] * n[:, 0] + K[0, 1] * n[:, 1] + K[0, 2], K[1, 1] * n[:, 1] + K[1, 2]])

    return to_px(xy_d), to_px(xy), z


def surface_tracks(
    vertices_table: np.ndarray,
    faces: np.ndarray,
    points_table: np.ndarray,
    colors_rgb: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray | None,
    size: tuple[int, int],
    Ts: np.ndarray,
    *,
    surface_tol_mm: float = 1.0,
    min_views: int = 2,
) -> ColmapTracks:
    """The views that see each point on a mesh (see the module docstring), for COLMAP's tracks.

    Parameters
    ----------
    vertices_table, faces : (N, 3) float mm, (M, 3) int
        The final mesh: it decides what is occluded.
    points_table : (P, 3) float
        mm, table frame; points further than ``surface_tol_mm`` from the mesh are dropped.
    colors_rgb : (P, 3) uint8
    K : (3, 3) float
        The original photos' camera matrix, pixel centres at integers.
    dist : (n,) float or None
        Their OpenCV distortion.
    size : (width, height)
        The photos' size, pixels.
    Ts : (V, 4, 4) float
        ``T_cam_table`` of each view, mm.
    surface_tol_mm : float
        How far a point may lie from the mesh, and how far before it the ray
        may first meet the mesh, and still count as seen.
    min_views : int
        Points seen by fewer views are dropped.
    """
    import open3d as o3d

    from .raycast import first_hits, raycasting_scene

    P = np.asarray(points_table, np.float64)
    C = np.asarray(colors_rgb, np.uint8)
    Ts = np.asarray(Ts, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or C.shape != P.shape:
        raise ValueError(f"points_table (P, 3) and colors_rgb (P, 3) expected, got {P.shape} and {C.shape}")
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
        raise ValueError(f"Ts: expected (V, 4, 4), got {Ts.shape}")
    scene = raycasting_scene(vertices_table, faces)
    normals = np.zeros((0, 3))
    if len(P):  # open3d's stubs make Tensor's dtype and device required; they are optional
        near = scene.compute_closest_points(o3d.core.Tensor(P.astype(np.float32)))  # type: ignore[call-overload]
        on = np.linalg.norm(near["points"].numpy() - P, axis=1) <= surface_tol_mm
        P, C, normals = P[on], C[on], near["primitive_normals"].numpy()[on].astype(np.float64)
    W, H = int(size[0]), int(size[1])
    visible = np.zeros((len(P), len(Ts)), bool)
    uv_all = np.full((len(P), len(Ts), 2), np.nan)
    for v, T in enumerate(Ts):
        uv, ideal, z = project_photo_px(K, dist, T, P)
        centre = camera_centre_table(T)
        facing = np.einsum("pd,pd->p", normals, centre - P) > 0  # the closest face turns towards the camera
        idx = np.flatnonzero((z > 1.0) & facing & _in_image(uv, W, H) & _in_image(ideal, W, H, margin=0.25))
        d = P[idx] - centre  # the ray reaches the point at parameter 1
        rays = np.hstack([np.broadcast_to(centre, d.shape), d]).astype(np.float32)
        t = first_hits(scene, rays) if len(idx) else np.zeros(0)
        seen = t >= 1.0 - surface_tol_mm / np.linalg.norm(d, axis=1)
        visible[idx[seen], v] = True
        uv_all[idx[seen], v] = uv[idx[seen]]
    keep = visible.sum(axis=1) >= min_views
    return ColmapTracks(P[keep], C[keep], visible[keep], uv_all[keep])


def _in_image(uv: np.ndarray, W: int, H: int, margin: float = 0.0) -> np.ndarray:
    """Inside the photo's pixel area ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``, grown by ``margin`` of its size."""
    mx, my = margin * W, margin * H
    return ((uv[:, 0] >= -0.5 - mx) & (uv[:, 0] < W - 0.5 + mx) &
            (uv[:, 1] >= -0.5 - my) & (uv[:, 1] < H - 0.5 + my))


# --- nerfstudio ------------------------------------------------------------------------------------


def export_nerfstudio(
    K: np.ndarray,
    width: int,
    height: int,
    frames: Sequence[tuple[str, np.ndarray]],
    out_dir: str | os.PathLike,
    *,
    dist: np.ndarray | None = None,
    ply_file_path: str | None = None,
) -> Path:
    """Write nerfstudio's ``transforms.json`` (camera-to-world, OpenGL camera axes, metres).

    Parameters
    ----------
    K : (3, 3) float
        Pixels, pixel centres at integers (converted to nerfstudio's +0.5).
    width, height : int
    frames : sequence of (image_name, T_cam_table)
        ``file_path`` is written as given: a path relative to ``out_dir``.
    out_dir : path
    dist : (4,) or (5,) float, optional
        OpenCV ``k1 k2 p1 p2[ k3]`` (zeros if omitted).
    ply_file_path : str, optional
        Relative path of a point cloud / mesh PLY in the same frame and unit
        (e.g. ``model.ply`` from :func:`export_mesh`) for splatfacto's
        initialisation.

    Returns
    -------
    Path
        The ``transforms.json`` written.
    """
    K, width, height, frames, d = _check_cameras(K, width, height, frames, dist)
    doc = {
        "camera_model": "OPENCV",
        "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5,
        "w": width, "h": height,
        "k1": d[0], "k2": d[1], "k3": d[4], "p1": d[2], "p2": d[3],
        "frames": [],
    }
    if ply_file_path is not None:
        doc["ply_file_path"] = str(ply_file_path)
    for name, T in frames:
        T_table_cam = np.linalg.inv(T)
        T_table_cam[:3, 3] /= MM_PER_M
        doc["frames"].append({"file_path": name, "transform_matrix": (T_table_cam @ _CV_TO_GL).tolist()})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "transforms.json"
    atomic_write_bytes(path, (json.dumps(doc, indent=2) + "\n").encode())
    return path
