"""An albedo texture baked from the calibrated photos into a mesh's UV atlas.

The atlas (projection charts, packing, levels of detail sharing one atlas) is
:mod:`recon.atlas`; :func:`uv_atlas` and :func:`uv_atlas_levels` are importable from here too.

**Bake** (:func:`bake_texture`): every texel inside a chart is a surface point
``X`` (barycentric mix of its face's corners) with a normal ``n``. For view
``k`` (pose ``T_cam_table = [R | t]``, centre ``C = -R^T t``) it projects to

    u ~ K (R X + t),

and is **seen** when it faces the camera (``cos θ = n · (C - X)/|C - X| >
min_cos``), lies inside the image and the (1 px eroded) silhouette, and the
mesh's own depth image (ray cast, :mod:`recon.raycast`) bilinearly sampled at
``u`` equals its depth within ``tol + 1.5 z tan θ / f`` — so the bilinear
footprint neither reaches past a silhouette nor across an occluding edge. Its
sample is the photo bilinearly interpolated at ``u`` (``cv2.remap``) in
*linear light* (IEC sRGB decoding), weighted by

    w = cos θ · (d₀ / d)² · feather,

where ``cos θ / d²`` is the area of the photo the surface element covers (every
photo pixel on it counts once; ``COS_POWER``) and ``feather`` in (0, 1]
grows with the distance to the nearest silhouette or depth edge in the photo
(``FEATHER_PX``), so a view fades out before it ends and seams between views
blend instead of stepping. Before blending, each view's **exposure gain**
``g_k`` is estimated from texels several views see: ``g_k = median_t (L_kt /
L̄_t)`` over a subsample, ``L̄_t`` the weighted mean of ``L_kt / g_k`` (a few
alternations, geometric mean of ``g`` fixed to 1). The texel's colour is
``Σ w_k I_k / g_k / Σ w_k``; texels no view sees take the interpolated vertex
colour; the texture is then stored sRGB-encoded (glTF's base-colour texture is
sRGB), and the empty texels around the charts are filled outward from the
chart edges (``DILATE_TEXELS`` rings, then the mean), so bilinear sampling and
mip-maps never pull in black background.

**Why cos θ, not a higher power** (measured 2026-12-02, ``benchmarks/texture.py``'s
held-out frames, 50k hull meshes): with ``cos⁴ θ`` the most frontal view dominated,
and the texture was 0.29 dB *below* the vertex colours' weighted median on the
synthetic sample. Its exposure gains were 1.00 ± 0.01 (not the cause), and a
weighted median or rejecting samples far from it did worse (sample 26.1 / 27.1 dB
against 27.3 for the mean). The cause: a turntable's light turns with the
camera in the table frame, so a point's shading differs from view to view, and
a hull surface off the true one projects to slightly different photo points in
each view; a held-out view is predicted best by the mean over the views, the
one static colour closest to all of them, and the mean also averages the
photos' noise. Held-out PSNR / SSIM, cos⁴ → cos¹ → cos⁰: sample 26.63 / 0.920 →
27.26 / 0.924 → 27.38 / 0.924, squirrel 20.00 / 0.796 → 20.36 / 0.804 → 20.39 /
0.803; cos¹ (each photo pixel counted once) is kept: the best SSIM on the real
object and frontal views still count more than grazing, blurred ones.

**Levels of detail** (:func:`texture_mesh` ``lods``): coarser meshes (quadric
decimation, :func:`decimate`) in the same atlas (:func:`uv_atlas_levels`: a texel stands
for the same surface point on every level), sharing the one texture.
Texels only a coarser level's faces cover (where it bulges past the finer
surface) are baked from the closest point of the finest mesh.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from calib.camera import as_K, as_poses, camera_centre_table

from .atlas import (
    ATLAS_FILL,
    PADDING_TEXELS,
    closest_faces,
    rasterize_faces,
    texel_barycentrics,
    uv_atlas,
    uv_atlas_levels,
)
from .raycast import first_hits, raycasting_scene
from .silhouettes import worker_threads
from .types import TableMesh

__all__ = ["TexturedMesh", "uv_atlas", "uv_atlas_levels", "bake_texture", "texture_mesh", "decimate",
           "render_albedo", "srgb_encode", "srgb_decode_lut"]

log = logging.getLogger(__name__)

#: Rings of empty texels filled from the charts' edges before the rest of the texture takes the mean colour.
DILATE_TEXELS = 8
#: A view's weight ramps from ~0 to 1 over this many pixels from a silhouette or depth edge.
FEATHER_PX = 8.0
#: Texels per photo pixel on the surface (closest view) that the texture side aims for (:func:`texture_side`).
TEXELS_PER_PIXEL = 2.0
#: Texels sampled to estimate the per-view exposure gains.
GAIN_SAMPLES = 40_000
#: Power of the viewing-angle cosine in a sample's weight (module docstring: why a low power).
COS_POWER = 1.0


@dataclass(frozen=True)
class TexturedMesh:
    """A mesh with a UV atlas and its baked albedo texture.

    Attributes
    ----------
    mesh : TableMesh
        Vertices (N', 3) mm in the table frame, split along the atlas' seams
        (N' >= N of the source mesh), normals and vertex colours carried over.
    texcoords : (N', 2) float32
        glTF convention: ``(0, 0)`` the top-left corner of the image, ``u``
        right, ``v`` down, in [0, 1].
    texture_rgb : (S, S, 3) uint8
        sRGB-encoded albedo.
    source_vertex : (N',) int64
        Index of each vertex in the source mesh.
    lods : tuple of TexturedMesh
        Coarser levels of detail (fewer faces, finest first) mapped into the same atlas: each one's
        ``texture_rgb`` is this one's array, its ``source_vertex`` indexes its own (decimated) mesh.
    """

    mesh: TableMesh
    texcoords: np.ndarray
    texture_rgb: np.ndarray
    source_vertex: np.ndarray
    lods: tuple[TexturedMesh, ...] = ()


# --------------------------------------------------------------------------- colour


def srgb_decode_lut() -> np.ndarray:
    """(256,) float32: 8-bit sRGB code -> linear light in [0, 1] (IEC 61966-2-1)."""
    c = np.arange(256, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_encode(lin: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] (any shape) -> 8-bit sRGB codes (uint8), IEC 61966-2-1 (float32 arithmetic)."""
    x = np.clip(np.asarray(lin, np.float32), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, np.float32(1 / 2.4)) - 0.055)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- bake


@dataclass(frozen=True)
class _Texels:
    """The surface points the texture stores: flat texel index, face, position (mm), unit normal."""

    flat: np.ndarray  # (P,) int64 into the (S * S) texture
    face: np.ndarray  # (P,) int64
    pts: np.ndarray  # (P, 3) float32, mm, table frame
    normals: np.ndarray  # (P, 3) float32, unit
    bary: np.ndarray  # (P, 3) float32


@dataclass(frozen=True)
class _ViewMaps:
    """One view's mesh depth (z, mm; 0 where no surface) and feather weight, over the crop ``x0, y0``."""

    depth: np.ndarray  # (h, w) float32
    feather: np.ndarray  # (h, w) float32 in [0, 1]
    x0: int
    y0: int


def texture_mesh(
    mesh: TableMesh,
    images_rgb: Sequence[np.ndarray],
    K: np.ndarray,
    T_cam_table: Sequence[np.ndarray] | np.ndarray,
    *,
    masks: Sequence[np.ndarray] | None = None,
    size: int = 2048,
    lods: Sequence[int] = (),
    progress: Callable[[int, int], None] | None = None,
) -> TexturedMesh:
    """UV atlas (:func:`uv_atlas`) plus baked texture (:func:`bake_texture`) of ``mesh``; see the module docstring.

    ``size`` is the largest texture side; the side used is :func:`texture_side` (no more texels than the
    photos resolve). ``lods``: face counts of coarser levels of detail (quadric decimation of ``mesh``,
    :func:`decimate`), all in one atlas (:func:`uv_atlas_levels`) sharing the one texture; a count not
    below the previous level's faces is left out.
    """
    V = np.asarray(mesh.vertices_table, np.float64)
    F = np.asarray(mesh.faces, np.int64)
    size = texture_side(V, F, K, T_cam_table, size)
    coarse: list[TableMesh] = []
    for n in sorted({int(n) for n in lods}, reverse=True):
        if n < len(coarse[-1].faces if coarse else F):
            coarse.append(decimate(mesh, n))
    atlas = uv_atlas_levels([(V, F)] + [(m.vertices_table, m.faces) for m in coarse], size)
    src, faces, uv = atlas[0]
    normals = _vertex_normals(mesh)
    colors = None if mesh.colors_rgb is None else np.asarray(mesh.colors_rgb, np.uint8)[src]
    split = TableMesh(V[src], faces, normals[src], colors)
    levels = [(TableMesh(np.asarray(m.vertices_table)[s], f, np.asarray(m.normals_table)[s]), u, s)
              for m, (s, f, u) in zip(coarse, atlas[1:], strict=True)]
    texture = bake_texture(split, uv, images_rgb, K, T_cam_table, masks=masks, size=size,
                           extra_levels=[(m, u) for m, u, _ in levels], progress=progress)
    return TexturedMesh(split, uv, texture, src, tuple(TexturedMesh(m, u, texture, s) for m, u, s in levels))


def decimate(mesh: TableMesh, max_faces: int) -> TableMesh:
    """A coarser level of detail: quadric decimation (open3d) of ``mesh`` to at most ``max_faces`` faces,
    degenerate faces dropped, vertex normals recomputed (no colours: the texture colours it)."""
    import open3d as o3d

    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices_table, np.float64)),
                                   o3d.utility.Vector3iVector(np.asarray(mesh.faces, np.int32)))
    om = om.simplify_quadric_decimation(target_number_of_triangles=int(max_faces))
    tm = trimesh.Trimesh(np.asarray(om.vertices), np.asarray(om.triangles, np.int64), process=True)
    tm.update_faces(tm.nondegenerate_faces())
    tm.remove_unreferenced_vertices()
    return TableMesh(np.asarray(tm.vertices), np.asarray(tm.faces, np.int64), np.asarray(tm.vertex_normals))


def texture_side(vertices_table: np.ndarray, faces: np.ndarray, K: np.ndarray,
                 T_cam_table: Sequence[np.ndarray] | np.ndarray, max_size: int) -> int:
    """Texture side (a power of two, 256 to ``max_size``) with at least ``TEXELS_PER_PIXEL`` texels per pixel the
    closest photo spends on the surface.

    The closest view's pixel footprint is ``s = d_min / f`` mm (``d_min`` the smallest camera distance to the
    mesh's centroid); the surface of area ``A`` covers ``A / s²`` such pixels, and charts fill about
    ``ATLAS_FILL`` of the texture: ``S² · ATLAS_FILL >= TEXELS_PER_PIXEL · A / s²``.
    """
    V = np.asarray(vertices_table, np.float64)
    F = np.asarray(faces, np.int64)
    tri = V[F]
    area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    Ts = as_poses(T_cam_table)
    centres = -np.einsum("kji,kj->ki", Ts[:, :3, :3], Ts[:, :3, 3])
    d_min = float(np.linalg.norm(centres - V.mean(axis=0), axis=1).min())
    K = as_K(K)
    footprint = d_min / float(np.sqrt(K[0, 0] * K[1, 1]))
    need = np.sqrt(TEXELS_PER_PIXEL * area / footprint**2 / ATLAS_FILL)
    side = 256
    while side < need and side < max_size:
        side *= 2
    return int(min(side, max_size))


def bake_texture(
    mesh: TableMesh,
    texcoords: np.ndarray,
    images_rgb: Sequence[np.ndarray],
    K: np.ndarray,
    T_cam_table: Sequence[np.ndarray] | np.ndarray,
    *,
    masks: Sequence[np.ndarray] | None = None,
    size: int = 2048,
    min_cos: float = 0.1,
    tol_mm: float | None = None,
    extra_levels: Sequence[tuple[TableMesh, np.ndarray]] = (),
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """The albedo texture of a mesh with texture coordinates, from undistorted photos.

    Parameters
    ----------
    mesh : TableMesh
        Vertices (N, 3) mm, table frame, outward faces (M, 3); ``colors_rgb``
        (sRGB) fill texels no view sees (grey without them).
    texcoords : (N, 2) float
        glTF texture coordinates in [0, 1] (see :class:`TexturedMesh`).
    images_rgb : sequence of (H, W, 3) uint8
        Undistorted sRGB photos, one per view, all of one size.
    K : (3, 3) float
        Their pinhole camera matrix, pixel centres at integers.
    T_cam_table : (V, 4, 4) float
        Table (mm) -> camera (mm) of each view.
    masks : sequence of (H, W) bool/uint8, optional
        Object silhouettes; samples only inside them.
    size : int
        Texture side, texels.
    min_cos : float
        Smallest cosine of the viewing angle that counts.
    tol_mm : float, optional
        Depth agreement for visibility; default the median edge length.
    extra_levels : sequence of (TableMesh, (N_l, 2) texcoords)
        Coarser levels of detail in the same atlas (:func:`uv_atlas_levels`): the texels only their
        faces cover are baked too, from the points of ``mesh`` closest to them.
    progress : callable(done, total), optional

    Returns
    -------
    (size, size, 3) uint8
        sRGB texture; row 0 is ``v = 0`` (glTF).
    """
    images = [np.asarray(im) for im in images_rgb]
    Ts = as_poses(T_cam_table)
    K = as_K(K)
    if len(images) != len(Ts) or not images:
        raise ValueError(f"need one pose per image: {len(images)} images, {len(Ts)} poses")
    if masks is not None and len(masks) != len(images):
        raise ValueError(f"masks: expected {len(images)}, got {len(masks)}")
    V = np.asarray(mesh.vertices_table, np.float64)
    F = np.asarray(mesh.faces, np.int64)
    uv = np.asarray(texcoords, np.float32)
    if uv.shape != (len(V), 2):
        raise ValueError(f"texcoords: expected {(len(V), 2)}, got {uv.shape}")
    tol = _median_edge(V, F) if tol_mm is None else float(tol_mm)
    scene = raycasting_scene(V, F)
    tex = _texels(mesh, uv, F, int(size), extra_levels, scene)
    lut = srgb_decode_lut()
    n_views = len(images)
    with ThreadPoolExecutor(max_workers=worker_threads()) as pool:  # numpy, OpenCV, Embree release the GIL
        maps = list(pool.map(lambda k: _view_maps(scene, V, K, Ts[k], images[k].shape[:2],
                                                  None if masks is None else np.asarray(masks[k]), tol),
                             range(n_views)))
        gains = _exposure_gains(tex, images, maps, K, Ts, lut, min_cos, tol)

        def samples(k):
            sel = np.flatnonzero(_facing_faces(V, F, Ts[k], min_cos)[tex.face])
            return _view_samples(tex, sel, images[k], maps[k], K, Ts[k], lut, min_cos, tol)

        acc = np.zeros((len(tex.flat), 3), np.float32)
        wsum = np.zeros(len(tex.flat), np.float32)
        step = 2 * worker_threads()  # a few views in flight: bounded memory
        for start in range(0, n_views, step):
            views = range(start, min(start + step, n_views))
            for k, (idx, w, rgb) in zip(views, pool.map(samples, views), strict=True):
                wsum[idx] += w  # idx holds each texel once: fancy-index adds are exact
                acc[idx] += rgb * (w / gains[k])[:, None]
                if progress is not None:
                    progress(k + 1, n_views)
    return _finish(tex, acc, wsum, mesh, F, int(size))


def _facing_faces(V: np.ndarray, F: np.ndarray, T: np.ndarray, min_cos: float) -> np.ndarray:
    """(M,) bool: faces some point of which may face the camera at more than ``min_cos`` (a cheap pre-filter).

    A face's corners are tested with the face normal; one corner passing (at half ``min_cos``, for the
    interpolated normals) keeps the face.
    """
    C = camera_centre_table(T)
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    to_cam = C - tri
    cos = np.einsum("md,mkd->mk", n, to_cam) / np.maximum(np.linalg.norm(to_cam, axis=2), 1e-12)
    return (cos > 0.5 * min_cos - 0.3).any(axis=1)


def _vertex_normals(mesh: TableMesh) -> np.ndarray:
    if mesh.normals_table is not None:
        return np.asarray(mesh.normals_table, np.float64)
    return np.asarray(trimesh.Trimesh(mesh.vertices_table, mesh.faces, process=False).vertex_normals, np.float64)


def _median_edge(V: np.ndarray, F: np.ndarray) -> float:
    e = V[F[:, [1, 2, 0]]] - V[F]
    return float(np.median(np.linalg.norm(e, axis=2)))


def _texels(mesh: TableMesh, uv: np.ndarray, F: np.ndarray, size: int,
            extra_levels: Sequence[tuple[TableMesh, np.ndarray]] = (), scene=None) -> _Texels:
    """The texels ``mesh``'s charts cover (grown by half the gutter), then those only a coarser level's
    faces cover (``extra_levels``: mesh, texcoords): each of those stands for the point of ``mesh`` closest
    to its point on that level, so every texel is a point of the finest surface."""
    face_id = rasterize_faces(uv, F, size, grow=PADDING_TEXELS // 2)
    flat, f, bary = texel_barycentrics(uv, F, size, face_id)
    if extra_levels:
        V64 = np.asarray(mesh.vertices_table, np.float64)
        scene = scene if scene is not None else raycasting_scene(V64, F)
        taken = face_id >= 0
        more_flat, more_f, more_bary = [flat], [f], [bary]
        for lod, lod_uv in extra_levels:
            FL = np.asarray(lod.faces, np.int64)
            lid = rasterize_faces(np.asarray(lod_uv, np.float32), FL, size, grow=PADDING_TEXELS // 2)
            lid[taken] = -1
            if not (lid >= 0).any():
                continue
            taken |= lid >= 0
            lflat, lf, lbary = texel_barycentrics(np.asarray(lod_uv, np.float32), FL, size, lid)
            p = np.einsum("pk,pkd->pd", lbary, np.asarray(lod.vertices_table, np.float64)[FL[lf]])
            cf, cb = closest_faces(scene, p)
            more_flat.append(lflat)
            more_f.append(cf)
            more_bary.append(cb)
        flat, f, bary = np.concatenate(more_flat), np.concatenate(more_f), np.concatenate(more_bary)
    V = np.asarray(mesh.vertices_table, np.float32)
    N = _vertex_normals(mesh).astype(np.float32)
    corners = F[f]
    pts = np.einsum("pk,pkd->pd", bary, V[corners])
    n = np.einsum("pk,pkd->pd", bary, N[corners])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return _Texels(flat, f, pts.astype(np.float32), n.astype(np.float32), bary)


def _view_maps(scene, V: np.ndarray, K: np.ndarray, T: np.ndarray, hw, mask, tol: float) -> _ViewMaps:
    """Depth of the mesh in a view (rays cast over the mesh's bounding box in the image only) and its feather."""
    H, W = hw
    R, t = T[:3, :3], T[:3, 3]
    pc = V @ R.T + t
    front = pc[:, 2] > 1e-6
    if not front.any():
        return _ViewMaps(np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32), 0, 0)
    uv = pc[front, :2] / pc[front, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    x0, y0 = (max(int(np.floor(uv[:, i].min())) - 2, 0) for i in (0, 1))
    x1, y1 = min(int(np.ceil(uv[:, 0].max())) + 3, W), min(int(np.ceil(uv[:, 1].max())) + 3, H)
    if x1 <= x0 or y1 <= y0:
        return _ViewMaps(np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32), 0, 0)
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d_cam[..., 0] -= K[0, 1] / K[0, 0] * d_cam[..., 1]
    C = camera_centre_table(T)
    rays = np.concatenate([np.broadcast_to(C, d_cam.shape), d_cam @ R], -1).astype(np.float32)
    z = first_hits(scene, rays)
    depth = np.where(np.isfinite(z), z, 0.0).astype(np.float32)
    good = depth > 0
    if mask is not None:
        m = (np.asarray(mask)[y0:y1, x0:x1] > 0).astype(np.uint8)
        good &= cv2.erode(m, np.ones((3, 3), np.uint8)) > 0
    # a depth edge: the 3x3 neighbourhood spans more than a few tolerances (an occluding contour)
    k3 = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(depth, k3) - cv2.erode(np.where(good, depth, 1e9).astype(np.float32), k3)) > 4.0 * tol
    good &= ~jump
    dist = cv2.distanceTransform(good.astype(np.uint8), cv2.DIST_L2, 3)
    feather = np.clip(dist / FEATHER_PX, 0.0, 1.0).astype(np.float32)
    return _ViewMaps(np.where(good, depth, 0.0).astype(np.float32), feather, x0, y0)


def _remap(img: np.ndarray, mx: np.ndarray, my: np.ndarray, border: float = 0.0) -> np.ndarray:
    """Bilinear samples of ``img`` at (mx, my) (pixel centres at integers), any number of points.

    ``cv2.remap`` wants 2-D maps of at most 32767 columns: the points are laid out in rows of 1024.
    """
    n = len(mx)
    cols = 1024
    rows = max(1, -(-n // cols))
    pad = rows * cols - n
    fx = np.concatenate([mx.astype(np.float32), np.full(pad, -1e4, np.float32)]).reshape(rows, cols)
    fy = np.concatenate([my.astype(np.float32), np.full(pad, -1e4, np.float32)]).reshape(rows, cols)
    out = cv2.remap(img, fx, fy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
    return out.reshape(rows * cols, *img.shape[2:])[:n]


def _view_samples(tex: _Texels, sel: np.ndarray, image: np.ndarray, maps: _ViewMaps, K: np.ndarray, T: np.ndarray,
                  lut: np.ndarray, min_cos: float, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels ``sel`` one view sees (see the module docstring): indices into the texels, weights, linear RGB."""
    R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
    C = camera_centre_table(T).astype(np.float32)
    P = tex.pts[sel]
    to_cam = C - P
    d = np.sqrt(np.einsum("pd,pd->p", to_cam, to_cam))
    cos = np.einsum("pd,pd->p", tex.normals[sel], to_cam) / np.maximum(d, 1e-6)
    keep = np.flatnonzero(cos > min_cos)
    P, d, cos = P[keep], d[keep], cos[keep]
    pc = P[:, 0:1] * R[:, 0] + P[:, 1:2] * R[:, 1] + P[:, 2:3] * R[:, 2] + t  # no BLAS: see colorize._apply
    z = np.maximum(pc[:, 2], 1e-6)
    u = K[0, 0] * pc[:, 0] / z + K[0, 1] * pc[:, 1] / z + K[0, 2]
    v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    mx, my = (u - maps.x0).astype(np.float32), (v - maps.y0).astype(np.float32)
    z_map = _remap(maps.depth, mx, my)
    tan = np.sqrt(np.maximum(1.0 - cos**2, 0.0)) / cos
    seen = (pc[:, 2] > 1e-6) & (np.abs(z_map - z) < tol + 1.5 * z * tan / K[0, 0])
    feather = _remap(maps.feather, mx, my)
    seen &= feather > 0
    keep, mx, my, d, cos, feather = keep[seen], mx[seen], my[seen], d[seen], cos[seen], feather[seen]
    h, w = maps.depth.shape
    crop = image[maps.y0:maps.y0 + h, maps.x0:maps.x0 + w]
    rgb = _remap(lut[crop], mx, my)
    weight = cos**COS_POWER * (1000.0 / d) ** 2 * feather
    return sel[keep], weight.astype(np.float32), rgb.astype(np.float32)


def _exposure_gains(tex: _Texels, images, maps, K, Ts, lut, min_cos: float, tol: float) -> np.ndarray:
    """(V,) per-view exposure gain from texels several views see (module docstring); 1 where unknown."""
    n_views = len(images)
    rng = np.random.default_rng(0)
    sel = np.sort(rng.choice(len(tex.flat), min(GAIN_SAMPLES, len(tex.flat)), replace=False))
    lum = np.zeros((len(sel), n_views), np.float32)
    wts = np.zeros((len(sel), n_views), np.float32)
    where = np.full(len(tex.flat), -1, np.int64)
    where[sel] = np.arange(len(sel))
    for k in range(n_views):
        idx, w, rgb = _view_samples(tex, sel, images[k], maps[k], K, Ts[k], lut, min_cos, tol)
        row = where[idx]
        lum[row, k] = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        wts[row, k] = w
    ok = (wts > 0) & (lum > 1e-3)
    multi = ok.sum(axis=1) >= 2
    lum, wts, ok = lum[multi], np.where(ok, wts, 0)[multi], ok[multi]
    gains = np.ones(n_views)
    if not len(lum):
        return gains
    for _ in range(4):
        ref = (wts * lum / gains).sum(axis=1) / wts.sum(axis=1)
        ratio = lum / np.maximum(ref, 1e-6)[:, None]
        for k in range(n_views):
            r = ratio[ok[:, k], k]
            gains[k] = float(np.median(r)) if len(r) >= 50 else 1.0
        gains /= np.exp(np.mean(np.log(gains)))
    log.debug("exposure gains: %s", np.round(gains, 3))
    return gains


def _finish(tex: _Texels, acc: np.ndarray, wsum: np.ndarray, mesh: TableMesh, F: np.ndarray, size: int) -> np.ndarray:
    """Blended texels, holes from the vertex colours, sRGB-encoded, the gutter filled outward."""
    lin = np.empty_like(acc)
    seen = wsum > 0
    lin[seen] = acc[seen] / wsum[seen, None]
    if not seen.all():
        lut = srgb_decode_lut()
        if mesh.colors_rgb is None:
            fill = np.full((int((~seen).sum()), 3), lut[128], np.float32)
        else:
            vc = lut[np.asarray(mesh.colors_rgb, np.uint8)]
            fill = np.einsum("pk,pkd->pd", tex.bary[~seen], vc[F[tex.face[~seen]]])
        lin[~seen] = fill
    S = int(size)
    img = np.zeros((S * S, 3), np.float32)
    filled = np.zeros(S * S, np.float32)
    img[tex.flat] = srgb_encode(lin).astype(np.float32)
    filled[tex.flat] = 1.0
    rgb, have = img.reshape(S, S, 3), filled.reshape(S, S)
    for _ in range(DILATE_TEXELS):  # push the charts' edge colours outward, one ring at a time
        s = cv2.blur(rgb * have[..., None], (3, 3))
        c = cv2.blur(have, (3, 3))
        ring = (have == 0) & (c > 0)
        rgb[ring] = s[ring] / c[ring, None]
        have[ring] = 1.0
    if (have == 0).any():
        rgb[have == 0] = rgb[have > 0].mean(axis=0)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- checking


def render_albedo(mesh: TableMesh, K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int], *,
                  texcoords: np.ndarray | None = None, texture_rgb: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's colour as a camera sees it, unlit: the texture, or without one the vertex colours.

    Ray cast (pixel centres at integers), then the hit's barycentrics interpolate the texture
    coordinates (texture sampled bilinearly) or the vertex colours, in linear light as a glTF
    renderer does, stored sRGB.

    Returns
    -------
    rgb : (H, W, 3) uint8
        sRGB; 0 where no surface.
    hit : (H, W) bool
    """
    import open3d as o3d

    W, H = int(size[0]), int(size[1])
    V = np.asarray(mesh.vertices_table, np.float64)
    F = np.asarray(mesh.faces, np.int64)
    K = as_K(K)
    T = np.asarray(T_cam_table, np.float64)
    R = T[:3, :3]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0], (v - K[1, 2]) / K[1, 1],
                      np.ones_like(u)], -1)
    rays = np.concatenate([np.broadcast_to(camera_centre_table(T), d_cam.shape), d_cam @ R], -1).astype(np.float32)
    hit_info = raycasting_scene(V, F).cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
    hit = np.isfinite(hit_info["t_hit"].numpy())
    prim = hit_info["primitive_ids"].numpy()[hit].astype(np.int64)
    b12 = hit_info["primitive_uvs"].numpy()[hit].astype(np.float64)
    bary = np.column_stack([1.0 - b12.sum(axis=1), b12])
    lut = srgb_decode_lut()
    if texture_rgb is not None and texcoords is not None:
        tex = np.asarray(texture_rgb, np.uint8)
        S = tex.shape[0]
        uv = np.einsum("pk,pkd->pd", bary, np.asarray(texcoords, np.float64)[F[prim]]) * [tex.shape[1], S] - 0.5
        lin = _remap(lut[tex], uv[:, 0], uv[:, 1])
    elif mesh.colors_rgb is not None:
        lin = np.einsum("pk,pkd->pd", bary, lut[np.asarray(mesh.colors_rgb, np.uint8)][F[prim]])
    else:
        lin = np.full((len(prim), 3), lut[128], np.float32)
    out = np.zeros((H, W, 3), np.uint8)
    out[hit] = srgb_encode(lin)
    return out, hit
