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
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from .fileio import atomic_write_bytes
from .types import TableMesh

if TYPE_CHECKING:
    from .texture import TexturedMesh

__all__ = ["export_mesh", "png_bytes", "export_colmap", "export_nerfstudio", "glb_bytes", "srgb_to_linear",
           "ColmapTracks", "surface_tracks", "sample_surface", "project_photo_px", "MAX_TRACK_POINTS", "lod_stem"]

MM_PER_M = 1000.0
# glTF material of a scan: vertex colours times white, dielectric, matte.
SCAN_MATERIAL = {
    "name": "scan",
    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.9},
    "doubleSided": False,
}
# OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
#: At most this many 3D points with tracks in a COLMAP export (fused points beyond it are subsampled).
MAX_TRACK_POINTS = 50_000


def export_mesh(mesh: TableMesh, out_dir: str | os.PathLike, *, stem: str = "model",
                textured: TexturedMesh | None = None) -> dict[str, Path]:
    """Write ``<stem>.glb``, ``<stem>.ply`` and ``<stem>.obj`` in metres.

    With ``textured`` (the same surface with a UV atlas and its texture,
    :mod:`recon.texture`), the GLB carries the texture as its material's
    ``baseColorTexture`` (no ``COLOR_0``) and the OBJ names ``<stem>.mtl``,
    whose ``map_Kd`` is ``<stem>_albedo.png``; the PLY keeps ``mesh``
    (watertight, vertex colours). Its levels of detail (``textured.lods``)
    are ``<stem>_lod1.glb``/``.obj``, ... sharing that texture and material.

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
        ``{"glb": path, "ply": path, "obj": path}``, and ``"mtl"``, ``"texture"`` with ``textured``
        (and ``"glb_lod1"``, ``"obj_lod1"``, ... with its levels of detail).
    """
    V, F, N, C = _mesh_arrays(mesh)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {ext: out / f"{stem}.{ext}" for ext in ("glb", "ply", "obj")}
    tm = _trimesh_m(V, F, N, C)
    atomic_write_bytes(paths["ply"], trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True))
    if textured is not None:
        paths.update(_export_textured(textured, out, stem))
        return paths
    atomic_write_bytes(paths["glb"], glb_bytes(V / MM_PER_M, F, N, C))
    obj = trimesh.exchange.obj.export_obj(tm, include_normals=True, include_color=C is not None,
                                          include_texture=False, header=None)
    atomic_write_bytes(paths["obj"], obj.encode())
    return paths


def png_bytes(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 RGB image as a PNG file."""
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("could not encode the texture as PNG")
    return buf.tobytes()


def lod_stem(stem: str, level: int) -> str:
    """File stem of a level of detail: ``stem`` itself for level 0, ``<stem>_lod<level>`` for coarser ones."""
    return stem if level == 0 else f"{stem}_lod{level}"


def _export_textured(textured: TexturedMesh, out: Path, stem: str) -> dict[str, Path]:
    """``<stem>.glb`` with the texture embedded, ``<stem>.obj`` + ``.mtl`` + ``<stem>_albedo.png``; each level
    of detail ``textured.lods[i - 1]`` as ``<stem>_lod<i>.glb`` (the same PNG embedded) and ``.obj`` (naming
    ``<stem>.mtl``: one material, one texture file for every level)."""
    png = png_bytes(textured.texture_rgb)
    paths = {"mtl": out / f"{stem}.mtl", "texture": out / f"{stem}_albedo.png"}
    atomic_write_bytes(paths["texture"], png)
    atomic_write_bytes(paths["mtl"], (f"# turntable: matte, the photo texture (sRGB)\nnewmtl scan\n"
                                      f"Ka 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 1\nillum 1\nd 1\n"
                                      f"map_Kd {paths['texture'].name}\n").encode())
    for i, level in enumerate((textured, *textured.lods)):
        V, F, N, _ = _mesh_arrays(level.mesh)
        uv = np.asarray(level.texcoords, np.float64)
        if uv.shape != (len(V), 2):
            raise ValueError(f"texcoords of level {i}: expected {(len(V), 2)}, got {uv.shape}")
        name, suffix = lod_stem(stem, i), "" if i == 0 else f"_lod{i}"
        glb, obj = out / f"{name}.glb", out / f"{name}.obj"
        atomic_write_bytes(glb, glb_bytes(V / MM_PER_M, F, N, texcoords=uv, texture_png=png))
        lines = [f"# turntable: metres, +Y up, table frame\nmtllib {paths['mtl'].name}\no {name}\n",
                 _rows("v", V / MM_PER_M, "{:.7g}"),
                 _rows("vt", np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]), "{:.7g}"),  # OBJ: v up from the bottom row
                 _rows("vn", N, "{:.6g}"), "usemtl scan\n"]
        f1 = np.asarray(F, np.int64) + 1
        lines.append("".join(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}\n" for a, b, c in f1.tolist()))
        atomic_write_bytes(obj, "".join(lines).encode())
        paths[f"glb{suffix}"], paths[f"obj{suffix}"] = glb, obj
    return paths


def _rows(tag: str, a: np.ndarray, fmt: str) -> str:
    line = tag + (" " + fmt) * a.shape[1] + "\n"
    return "".join(line.format(*row) for row in a.tolist())


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
              colors_rgb: np.ndarray | None = None, *, texcoords: np.ndarray | None = None,
              texture_png: bytes | None = None) -> bytes:
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
        sRGB vertex colours; stored as linear float RGBA ``COLOR_0``. Not with a texture
        (``COLOR_0`` would multiply it).
    texcoords : (N, 2) float, optional
        ``TEXCOORD_0`` (glTF: origin at the image's top-left corner, v down), with ``texture_png``.
    texture_png : bytes, optional
        The sRGB base-colour texture as a PNG file, embedded in the binary chunk.
    """
    if (texcoords is None) != (texture_png is None) or (texture_png is not None and colors_rgb is not None):
        raise ValueError("give texcoords with texture_png, and no colors_rgb with a texture")
    n = np.asarray(normals, np.float64)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), (0.0, 1.0, 0.0))  # glTF: NORMAL must be unit
    arrays: list[np.ndarray] = [np.asarray(vertices_m, np.float32), n.astype(np.float32)]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if colors_rgb is not None:
        lin = srgb_to_linear(np.asarray(colors_rgb, np.float64) / 255.0)
        arrays.append(np.hstack([lin, np.ones((len(lin), 1))]).astype(np.float32))
        attributes["COLOR_0"] = 2
    if texcoords is not None:
        arrays.append(np.asarray(texcoords, np.float32).reshape(-1, 2))
        attributes["TEXCOORD_0"] = len(arrays) - 1
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
    material = dict(SCAN_MATERIAL)
    blobs = [a.tobytes() for a in arrays]
    extra: dict = {}
    if texture_png is not None:  # the image's own buffer view (no target), padded to 4 bytes
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(texture_png)})
        blobs.append(texture_png + b"\0" * (-len(texture_png) % 4))
        offset += len(blobs[-1])
        extra = {"images": [{"bufferView": len(views) - 1, "mimeType": "image/png"}],
                 "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
                 "textures": [{"sampler": 0, "source": 0}]}
        material["pbrMetallicRoughness"] = {**SCAN_MATERIAL["pbrMetallicRoughness"],  # type: ignore[dict-item]
                                            "baseColorTexture": {"index": 0}}
    gltf = {
        "asset": {"version": "2.0", "generator": "turntable recon.export",
                  "extras": {"units": "m", "frame": "table: origin at the pattern centre, +Y up"}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "model"}],
        "meshes": [{"name": "model", "primitives": [
            {"attributes": attributes, "indices": len(arrays) - 1, "material": 0, "mode": 4}]}],
        "materials": [material],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
        **extra,
    }
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(blobs)
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
        centre = -T[:3, :3].T @ T[:3, 3]
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


def sample_surface(mesh: TableMesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points spread evenly over a mesh's surface (area-weighted) with their interpolated colours.

    Returns
    -------
    points_table : (n, 3) float64
        mm, on the surface.
    colors_rgb : (n, 3) uint8
        Barycentric mix of the face's vertex colours (grey without colours).
    """
    V, F, _, C = _mesh_arrays(mesh)
    rng = np.random.default_rng(seed)
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(F), size=int(n), p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(int(n))), rng.random(int(n))
    bary = np.column_stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2])  # uniform on each triangle
    pts = np.einsum("nk,nkd->nd", bary, tri[face])
    if C is None:
        return pts, np.full((len(pts), 3), 128, np.uint8)
    cols = np.einsum("nk,nkd->nd", bary, C[F[face]].astype(np.float64))
    return pts, np.clip(np.rint(cols), 0, 255).astype(np.uint8)


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


# --- USDZ ------------------------------------------------------------------------------------------


def usd_available() -> bool:
    """Whether ``usd-core`` (``pxr``) is installed: the optional extra ``turntable[usd]``."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def export_usdz(textured: TexturedMesh, path: str | os.PathLike) -> Path:
    """Write a USDZ (AR Quick Look, Apple Vision Pro) of a textured mesh: metres, +Y up, UsdPreviewSurface.

    The package holds one ``.usdc`` layer (``metersPerUnit`` 1, ``upAxis`` Y; the mesh counter-clockwise
    seen from outside, USD's right-handed default) with ``primvars:st`` (USD's t runs up: ``1 - v``), a
    matte, non-metallic ``UsdPreviewSurface`` whose ``diffuseColor`` reads the sRGB PNG texture, and the
    texture itself. Needs ``usd-core`` (:func:`usd_available`).
    """
    import tempfile

    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils, Vt

    V, F, N, _ = _mesh_arrays(textured.mesh)
    uv = np.asarray(textured.texcoords, np.float64)
    with tempfile.TemporaryDirectory(prefix="usdz") as tmp:
        layer, tex = Path(tmp) / "model.usdc", Path(tmp) / "model_albedo.png"
        tex.write_bytes(png_bytes(textured.texture_rgb))
        stage = Usd.Stage.CreateNew(str(layer))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, "/model")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, "/model/scan")
        pts = V / MM_PER_M
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*pts.min(axis=0).tolist()), Gf.Vec3f(*pts.max(axis=0).tolist())]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(F), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(F.astype(np.int32).ravel()))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(N.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)))
        material = UsdShade.Material.Define(stage, "/model/scan_material")
        surface = UsdShade.Shader.Define(stage, "/model/scan_material/surface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.9)
        reader = UsdShade.Shader.Define(stage, "/model/scan_material/st_reader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        image = UsdShade.Shader.Define(stage, "/model/scan_material/albedo")
        image.CreateIdAttr("UsdUVTexture")
        image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(tex.name)
        image.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        image.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(image.ConnectableAPI(), "rgb")
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        stage.GetRootLayer().Save()
        packed = Path(tmp) / "model.usdz"
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(packed)):
            raise ValueError("usd-core could not package the USDZ")
        out = Path(path)
        atomic_write_bytes(out, _zip_times_fixed(packed.read_bytes()))
    return out


def _zip_times_fixed(data: bytes) -> bytes:
    """A zip (USDZ) with every entry's DOS time stamp set to 1980-01-01 00:00: the same model, the same bytes."""
    import io
    import zipfile

    buf = bytearray(data)
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        infos = z.infolist()
        start = z.start_dir  # the central directory's offset (CPython keeps it on the ZipFile)
    fixed = struct.pack("<HH", 0, (0 << 9) | (1 << 5) | 1)  # time 00:00:00, date 1980-01-01
    for info in infos:
        if buf[info.header_offset:info.header_offset + 4] == b"PK\x03\x04":
            buf[info.header_offset + 10:info.header_offset + 14] = fixed
    pos = start
    while buf[pos:pos + 4] == b"PK\x01\x02":
        buf[pos + 12:pos + 16] = fixed
        n, m, k = struct.unpack("<HHH", buf[pos + 28:pos + 34])
        pos += 46 + n + m + k
    return bytes(buf)
