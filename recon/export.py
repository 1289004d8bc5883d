"""Files for other tools: the mesh (GLB, PLY, OBJ) and the cameras (COLMAP, nerfstudio).

Every file is in **metres** in the table frame (origin at the pattern centre on
the table plane, +Y up, right-handed), which is already glTF's frame, so the
only conversion is ``p_m = p_mm / 1000``. Files are written whole or not at
all (temporary file, then ``os.replace``).

Conversions at this edge:

* **glTF colours**: ``COLOR_0`` is a *linear* multiplier (glTF 2.0 §3.7.2.1)
  while photos are sRGB, so the GLB stores ``srgb_to_linear(rgb / 255)`` as
  float RGBA; PLY/OBJ keep the sRGB bytes (what MeshLab and Blender's PLY
  importer expect). The GLB carries one non-metallic material
  (``metallicFactor`` 0, ``roughnessFactor`` 0.9, white base colour) so the
  vertex colours show as they are instead of glTF's default metal.
* **Pixels**: our pixel centres sit at integers; COLMAP and nerfstudio put the
  top-left pixel's centre at (0.5, 0.5), so ``cx, cy`` gain 0.5 there.
* **Poses**: COLMAP stores world-to-camera (``R_cam_table`` as a Hamilton
  quaternion ``qw qx qy qz`` and ``t_cam_table`` in metres), OpenCV camera
  axes; nerfstudio stores camera-to-world (``T_table_cam``) with OpenGL camera
  axes (x right, y up, z back): ``c2w = T_table_cam @ diag(1, -1, -1, 1)``.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from .fileio import atomic_write_bytes
from .types import TableMesh

__all__ = ["export_mesh", "export_colmap", "export_nerfstudio", "glb_bytes", "srgb_to_linear"]

MM_PER_M = 1000.0
# glTF material of a scan: vertex colours times white, dielectric, matte.
SCAN_MATERIAL = {
    "name": "scan",
    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.9},
    "doubleSided": False,
}
# OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def export_mesh(mesh: TableMesh, out_dir: str | os.PathLike, *, stem: str = "model") -> dict[str, Path]:
    """Write ``<stem>.glb``, ``<stem>.ply`` and ``<stem>.obj`` in metres.

    Parameters
    ----------
    mesh : TableMesh
        Vertices (N, 3) mm in the table frame, outward faces; normals are
        computed if missing, colours are optional.
    out_dir : path
        Created if missing.
    stem : str
        File name without extension.

    Returns
    -------
    dict
        ``{"glb": path, "ply": path, "obj": path}``.
    """
    V, F, N, C = _mesh_arrays(mesh)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {ext: out / f"{stem}.{ext}" for ext in ("glb", "ply", "obj")}
    atomic_write_bytes(paths["glb"], glb_bytes(V / MM_PER_M, F, N, C))
    tm = _trimesh_m(V, F, N, C)
    atomic_write_bytes(paths["ply"], trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True))
    obj = trimesh.exchange.obj.export_obj(tm, include_normals=True, include_color=C is not None,
                                          include_texture=False, header=None)
    atomic_write_bytes(paths["obj"], obj.encode())
    return paths


def _mesh_arrays(mesh: TableMesh):
    V = np.asarray(mesh.vertices_table, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise ValueError(f"vertices_table: expected (N, 3) with N > 0, got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"faces: expected (M, 3) indices into {len(V)} vertices, got {F.shape}")
    if mesh.normals_table is None:
        N = np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals, dtype=np.float64)
    else:
        N = np.asarray(mesh.normals_table, dtype=np.float64)
    C = None if mesh.colors_rgb is None else np.asarray(mesh.colors_rgb, dtype=np.uint8)
    for name, a in (("normals_table", N), ("colors_rgb", C)):
        if a is not None and a.shape != V.shape:
            raise ValueError(f"{name}: expected {V.shape}, got {a.shape}")
    return V, F, N, C


def _trimesh_m(V, F, N, C) -> trimesh.Trimesh:
    """trimesh in metres, vertex order kept (``process=False``)."""
    colors = None if C is None else np.hstack([C, np.full((len(C), 1), 255, np.uint8)])
    return trimesh.Trimesh(V / MM_PER_M, F, vertex_normals=N, vertex_colors=colors, process=False)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(vertices_m: np.ndarray, faces: np.ndarray, normals: np.ndarray,
              colors_rgb: np.ndarray | None = None) -> bytes:
    """A binary glTF 2.0 file of one triangle mesh with one non-metallic material.

    Parameters
    ----------
    vertices_m : (N, 3) float
        Positions in metres, glTF frame (+Y up, right-handed).
    faces : (M, 3) int
        Counter-clockwise seen from outside (glTF's front faces).
    normals : (N, 3) float
        Unit vertex normals.
    colors_rgb : (N, 3) uint8, optional
        sRGB vertex colours; stored as linear float RGBA ``COLOR_0``.
    """
    n = np.asarray(normals, np.float64)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), (0.0, 1.0, 0.0))  # glTF: NORMAL must be unit
    arrays: list[np.ndarray] = [np.asarray(vertices_m, np.float32), n.astype(np.float32)]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if colors_rgb is not None:
        lin = srgb_to_linear(np.asarray(colors_rgb, np.float64) / 255.0)
        arrays.append(np.hstack([lin, np.ones((len(lin), 1))]).astype(np.float32))
        attributes["COLOR_0"] = 2
    arrays.append(np.asarray(faces, np.uint32).ravel())

    views, accessors, offset = [], [], 0
    for i, a in enumerate(arrays):
        is_index = i == len(arrays) - 1
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": a.nbytes,
                      "target": 34963 if is_index else 34962})
        acc = {"bufferView": i, "componentType": 5125 if is_index else 5126,
               "count": int(a.size if is_index else len(a)),
               "type": "SCALAR" if is_index else f"VEC{a.shape[1]}"}
        if i == 0:  # POSITION requires bounds
            acc["min"], acc["max"] = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        accessors.append(acc)
        offset += a.nbytes  # every array is a multiple of 4 bytes long
    gltf = {
        "asset": {"version": "2.0", "generator": "turntable recon.export",
                  "extras": {"units": "m", "frame": "table: origin at the pattern centre, +Y up"}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "model"}],
        "meshes": [{"name": "model", "primitives": [
            {"attributes": attributes, "indices": len(arrays) - 1, "material": 0, "mode": 4}]}],
        "materials": [SCAN_MATERIAL],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
    }
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(a.tobytes() for a in arrays)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(js), b"JSON"), js,
                     struct.pack("<I4s", len(binary), b"BIN\0"), binary])


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
        (an initialisation for Gaussian splatting); none by default.
    colors_rgb : (P, 3) uint8, optional
        Their colours (grey if omitted).

    Returns
    -------
    dict
        ``{"cameras": path, "images": path, "points3D": path}``.
    """
    K, width, height, frames, d = _check_cameras(K, width, height, frames, dist)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            "# Number of cameras: 1", _colmap_camera_line(K, width, height, d)]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(frames)}, mean observations per image: 0"]
    for i, (name, T) in enumerate(frames, start=1):
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        q = np.array([qw, qx, qy, qz]) * (1.0 if qw >= 0 else -1.0)
        t_m = T[:3, 3] / MM_PER_M
        imgs.append(f"{i} " + " ".join(f"{x:.17g}" for x in (*q, *t_m)) + f" 1 {name}")
        imgs.append("")
    pts = _colmap_points(points_table, colors_rgb)
    paths = {"cameras": out / "cameras.txt", "images": out / "images.txt", "points3D": out / "points3D.txt"}
    atomic_write_bytes(paths["cameras"], ("\n".join(cams) + "\n").encode())
    atomic_write_bytes(paths["images"], ("\n".join(imgs) + "\n").encode())
    atomic_write_bytes(paths["points3D"], ("\n".join(pts) + "\n").encode())
    return paths


def _colmap_points(points_table, colors_rgb) -> list[str]:
    P = np.zeros((0, 3)) if points_table is None else np.asarray(points_table, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points_table: expected (P, 3), got {P.shape}")
    C = np.full((len(P), 3), 128, np.uint8) if colors_rgb is None else np.asarray(colors_rgb, np.uint8)
    if C.shape != P.shape:
        raise ValueError(f"colors_rgb: expected {P.shape}, got {C.shape}")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(P)}, mean track length: 0"]
    P_m = P / MM_PER_M
    lines += [f"{i} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {c[0]} {c[1]} {c[2]} 0"
              for i, (p, c) in enumerate(zip(P_m, C, strict=True), start=1)]
    return lines


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
