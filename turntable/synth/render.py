"""Ray-cast rendering of a turntable scene with exact pixel-centre geometry.

A view of a :class:`~turntable.synth.scene.SynthScene` is the camera pose
``T_cam_table`` plus the turntable's rotation ``T_world_table`` (table -> room;
identity for a hand-held sequence): camera rays are cast into the turntable
scene in table coordinates and into the room scene in world coordinates, and
the nearer hit wins.

Rays: output pixel ``(u, v)`` (pixel centres at integers, README conventions),
supersampled on an s x s grid inside the pixel, is mapped to the normalised
undistorted image point ``x`` that OpenCV's model distorts onto it
(``cv2.projectPoints(X, ..., K, dist) == (u, v)`` for ``X`` on the ray), solved by
Newton's method to 1e-12; the ray is ``(x, y, 1)`` in the camera frame.

Shading, in linear light, then sRGB-encoded (gamma 1/2.2)::

    c = albedo * (ambient * (0.55 + 0.45 n.up) + diffuse * max(n.l, 0) * vis)
        + specular * vis * max(n.h, 0)^shininess

with ``l`` a directional light fixed in the world (jittered over a small cone
per sub-sample: soft shadows), ``vis`` its visibility from the hit point (shadow
rays against the turntable scene: the object shades the target), ``h`` the
half vector. Sub-samples are averaged in linear light.
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from calib.camera import invert_T
from calib.types import as_points

from .scene import BACKDROPS, ROOM_HEIGHT_MM, WALL_MM_PER_PX, SynthScene, build_scene, gamma22_to_linear

__all__ = ["SynthScene", "build_scene", "render_view", "pixel_rays_cam", "undistort_normalized",
           "BACKDROPS"]

_BAND_PIXELS = 1 << 16  # pixels rendered per batch (memory bound)


# --------------------------------------------------------------------------- rays
def undistort_normalized(uv_px: np.ndarray, K: np.ndarray, dist=None, iterations: int = 20) -> np.ndarray:
    """Normalised undistorted points (N, 2) that OpenCV's model maps onto ``uv_px``.

    Inverts ``cv2.projectPoints``' distortion ``k1, k2, p1, p2[, k3]`` (radial and
    tangential) by Newton's method from the distorted point; exact to ~1e-12
    for distortions a lens can have (the map must be monotonic over the image).
    """
    uv = as_points(uv_px, 2, "uv_px")
    K = np.asarray(K, float)
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    d = np.zeros(5) if dist is None else np.asarray(dist, float).ravel()
    if d.size == 0 or not np.any(d):
        return np.column_stack([xd, yd])
    if d.size > 5 and np.any(d[5:]):
        raise ValueError("only k1, k2, p1, p2, k3 distortion is supported")
    k1, k2, p1, p2, k3 = np.concatenate([d, np.zeros(5)])[:5]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = 2.0 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d rad / d(x) = drad * x
        fx = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        a = rad + x * x * drad + 2 * p1 * y + 6 * p2 * x
        b = x * y * drad + 2 * p1 * x + 2 * p2 * y
        c = x * y * drad + 2 * p1 * x + 2 * p2 * y
        e = rad + y * y * drad + 6 * p1 * y + 2 * p2 * x
        det = a * e - b * c
        dx = (e * fx - b * fy) / det
        dy = (a * fy - c * fx) / det
        x -= dx
        y -= dy
        if max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) < 1e-14:
            break
    return np.column_stack([x, y])


def _subpixel_offsets(s: int) -> np.ndarray:
    o = (np.arange(s) + 0.5) / s - 0.5
    return np.stack(np.meshgrid(o, o, indexing="xy"), axis=-1).reshape(-1, 2)  # (s*s, 2) du, dv


def pixel_rays_cam(K: np.ndarray, uv_px: np.ndarray, dist=None) -> np.ndarray:
    """Unit ray directions (N, 3) float64 in the camera frame through pixel points ``uv_px`` (N, 2)."""
    xy = undistort_normalized(uv_px, K, dist)
    d = np.column_stack([xy, np.ones(len(xy))])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# --------------------------------------------------------------------------- shading
# surface classes of a sample (pixels whose 4-neighbours differ get supersampled)
_MISS, _OBJECT, _DISC_TOP, _DISC_SIDE, _FLOOR, _WALL = range(6)
_AA_LUMA_STEP = 0.05  # sRGB step to a neighbour that triggers supersampling


def _light_dirs(scene: SynthScene, n: int) -> np.ndarray:
    """``n`` unit light directions (n, 3) spread over the light's cone (a spiral)."""
    L = scene.light_dir_world
    if n == 1:
        return L[None, :].astype(np.float32)
    e1 = np.cross(L, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(L, e1)
    k = np.arange(n)
    rad = scene.light_cone_rad * np.sqrt((k + 0.5) / n)
    ang = k * 2.39996323  # golden angle
    dirs = L + rad[:, None] * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    return (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)


def _bilinear(img: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Bilinear samples (K, 3) float32 of an (h, w, 3) raster at fractional (row, col).

    ``cv2.remap`` (weights quantised to 1/32 texel), clamped at the border.
    """
    k = len(i)
    cols = 1024
    rows = max(1, -(-k // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:k], my[:k] = j, i
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:k]


def _object_surface(scene: SynthScene, prim: np.ndarray, bary_uv: np.ndarray, p_table: np.ndarray):
    """Linear albedo (K, 3) and unit shading normals (K, 3), table frame, of object hits."""
    f = scene.faces[prim]
    w = np.column_stack([1.0 - bary_uv[:, 0] - bary_uv[:, 1], bary_uv[:, 0], bary_uv[:, 1]])
    n = np.einsum("kj,kjc->kc", w, scene.vertex_normals[f])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    fn = scene.face_normals[prim]
    sharp = np.einsum("kc,kc->k", n, fn) < np.cos(np.radians(30.0))  # a crease: flat shading
    n[sharp] = fn[sharp]
    if scene.albedo is not None:
        rgb = scene.albedo(p_table)
    else:
        rgb = np.einsum("kj,kjc->kc", w, scene.vertex_rgb[f])
    return gamma22_to_linear(rgb), n.astype(np.float32)


def _room_albedo(scene: SynthScene, p_world: np.ndarray, gid: np.ndarray) -> np.ndarray:
    """Linear albedo (K, 3) of room hits (geometry ids ``gid``): table top, wall, backdrop."""
    is_floor = gid == scene.floor_id
    rgb = np.empty((len(p_world), 3), np.float32)
    pf = p_world[is_floor]
    c = (scene.floor_linear.shape[0] - 1) / 2.0
    rgb[is_floor] = _bilinear(scene.floor_linear, pf[:, 2] * scene.floor_px_per_mm + c,
                              pf[:, 0] * scene.floor_px_per_mm + c)
    pw = p_world[~is_floor]
    h, w = scene.wall_linear.shape[:2]
    col = (np.arctan2(pw[:, 2], pw[:, 0]) + np.pi) / (2 * np.pi) * w
    flat = gid[~is_floor] == scene.backdrop_id  # flat backdrop: columns along X
    col[flat] = pw[flat, 0] / WALL_MM_PER_PX + 0.25 * w
    row = (ROOM_HEIGHT_MM - pw[:, 1]) / WALL_MM_PER_PX
    rgb[~is_floor] = _bilinear(scene.wall_linear, row, np.mod(col, w - 1))
    return rgb


def _cast(rc: o3d.t.geometry.RaycastingScene, origin: np.ndarray, dirs: np.ndarray) -> dict:
    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = dirs
    out = rc.cast_rays(o3d.core.Tensor(rays))
    return {k: v.numpy() for k, v in out.items()}


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rows ``v`` (N, 3) rotated by ``R`` (3, 3): ``v @ R.T`` as float32, without BLAS.

    (A thin matmul through BLAS was 20x slower here on a loaded 2-core machine.)
    """
    R = np.asarray(R, np.float32)
    v = np.asarray(v, np.float32)
    return v[:, 0:1] * R[:, 0] + v[:, 1:2] * R[:, 1] + v[:, 2:3] * R[:, 2]


def _shade(scene: SynthScene, d_cam: np.ndarray, L_world: np.ndarray, T_table_cam: np.ndarray,
           T_world_table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (N, 3) float32 and surface class (N,) of unit camera rays ``d_cam`` (N, 3).

    ``L_world`` (N, 3) is the light direction used for each ray (soft shadows).
    """
    R_tc, o_t = T_table_cam[:3, :3], T_table_cam[:3, 3]
    R_wt, t_wt = T_world_table[:3, :3], T_world_table[:3, 3]
    d_t = _rotate(d_cam, R_tc)
    d_w = _rotate(d_t, R_wt)
    o_w = R_wt @ o_t + t_wt
    ht = _cast(scene.turntable, o_t, d_t)
    hr = _cast(scene.room, o_w, d_w)
    in_tt = ht["t_hit"] <= hr["t_hit"]
    t = np.where(in_tt, ht["t_hit"], hr["t_hit"])
    hit = np.isfinite(t)
    gid = np.where(in_tt, ht["geometry_ids"], hr["geometry_ids"])
    n = len(d_cam)
    cls = np.full(n, _MISS, np.int8)
    nrm = np.where(in_tt[:, None], ht["primitive_normals"], hr["primitive_normals"])
    is_obj = hit & in_tt & (gid == scene.object_id)
    is_disc = hit & in_tt & (gid == scene.disc_id)
    cls[is_obj] = _OBJECT
    cls[hit & ~in_tt] = np.where(gid[hit & ~in_tt] == scene.floor_id, _FLOOR, _WALL)
    tt = np.where(hit, t, 0.0).astype(np.float32)[:, None]
    p_t = o_t.astype(np.float32) + tt * d_t
    cls[is_disc] = np.where(p_t[is_disc, 1] > -0.01, _DISC_TOP, _DISC_SIDE)
    albedo = np.empty((n, 3), np.float32)
    albedo[:] = scene.wall_linear[::8, ::8].mean(axis=(0, 1))
    normal_t = nrm.astype(np.float32)  # table frame for turntable hits; fixed below for the room
    spec = np.full(n, 0.01, np.float32)
    if np.any(is_obj):
        albedo[is_obj], normal_t[is_obj] = _object_surface(
            scene, ht["primitive_ids"][is_obj].astype(np.int64), ht["primitive_uvs"][is_obj], p_t[is_obj])
        spec[is_obj] = scene.specular
    top = cls == _DISC_TOP
    if np.any(top):
        c = (scene.disc_top_linear.shape[0] - 1) / 2.0
        ppm = scene.disc_top_px_per_mm
        albedo[top] = _bilinear(scene.disc_top_linear, p_t[top, 2] * ppm + c, p_t[top, 0] * ppm + c)
        spec[top] = 0.02
    albedo[cls == _DISC_SIDE] = scene.disc_side_linear
    room = hit & ~in_tt
    if np.any(room):
        p_w = o_w.astype(np.float32) + tt[room] * d_w[room]
        albedo[room] = _room_albedo(scene, p_w, gid[room])
        normal_t[room] = _rotate(nrm[room], R_wt.T)  # world -> table
    flip = ~is_obj & (np.einsum("kc,kc->k", normal_t, d_t) > 0)  # face the camera
    normal_t[flip] *= -1.0

    L_t = _rotate(L_world, R_wt.T)
    ndl = np.einsum("kc,kc->k", normal_t, L_t)
    vis = np.zeros(n, np.float32)
    lit = hit & (ndl > 0)
    if np.any(lit):
        rays = np.concatenate([p_t[lit] + 0.03 * normal_t[lit], L_t[lit]], axis=1)
        vis[lit] = ~scene.turntable.test_occlusions(o3d.core.Tensor(rays), tnear=0.02).numpy()
    up_t = R_wt[1, :]  # world +Y in the table frame
    up = normal_t[:, 0] * up_t[0] + normal_t[:, 1] * up_t[1] + normal_t[:, 2] * up_t[2]
    h = L_t - d_t
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    ndh = np.clip(np.einsum("kc,kc->k", normal_t, h), 0, 1)
    diffuse = scene.diffuse * np.clip(ndl, 0, None) * vis
    shade = scene.ambient * (0.55 + 0.45 * up) + diffuse
    rgb = albedo * shade[:, None] + (spec * vis * (ndl > 0) * ndh ** scene.shininess)[:, None]
    return rgb, cls


def _render_pixels(scene, K, dist, uv_px, s, T_table_cam, T_wt, light_dirs):
    """Mean linear RGB (P, 3), object coverage (P,) and class of the first sample (P,)."""
    offs = _subpixel_offsets(s) if s > 1 else np.zeros((1, 2))
    n_sub = len(offs)
    P = len(uv_px)
    lin = np.empty((P, 3), np.float32)
    cover = np.empty(P, np.float32)
    cls0 = np.empty(P, np.int8)
    step = max(1, _BAND_PIXELS // n_sub)
    for a in range(0, P, step):
        uv = uv_px[a:a + step]
        d_cam = pixel_rays_cam(K, (uv[:, None, :] + offs[None]).reshape(-1, 2), dist)
        L = np.tile(light_dirs[:n_sub], (len(uv), 1))
        rgb, cls = _shade(scene, d_cam, L, T_table_cam, T_wt)
        lin[a:a + step] = rgb.reshape(-1, n_sub, 3).mean(axis=1)
        cls = cls.reshape(-1, n_sub)
        cover[a:a + step] = (cls == _OBJECT).mean(axis=1)
        cls0[a:a + step] = cls[:, 0]
    return lin, cover, cls0


def _needs_aa(cls: np.ndarray, srgb: np.ndarray) -> np.ndarray:
    """Pixels (H, W) bool whose class or brightness differs from a 4-neighbour's."""
    luma = srgb.mean(axis=2)
    flag = np.zeros(cls.shape, bool)
    for axis in (0, 1):
        dc = np.diff(cls, axis=axis) != 0
        dl = np.abs(np.diff(luma, axis=axis)) > _AA_LUMA_STEP
        d = dc | dl
        if axis == 0:
            flag[1:] |= d
            flag[:-1] |= d
        else:
            flag[:, 1:] |= d
            flag[:, :-1] |= d
    return flag


def _encode_srgb(lin: np.ndarray) -> np.ndarray:
    """Linear light -> uint8 by the power 1/2.2 (the inverse of :func:`gamma22_to_linear`), through a LUT."""
    lut = np.round(np.power(np.linspace(0.0, 1.0, 4096), 1.0 / 2.2) * 255.0).astype(np.uint8)
    return lut[np.clip(np.round(lin * 4095.0), 0, 4095).astype(np.int64)]


def render_view(scene: SynthScene, K: np.ndarray, T_cam_table: np.ndarray, size: tuple[int, int],
                dist=None, supersample: int = 3, T_world_table: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Render one noise-free view.

    Every pixel is first shaded by one ray through its centre; pixels whose
    surface class (object, disc top, disc rim, table, wall, nothing) or
    brightness differs from a 4-neighbour's are then re-rendered with
    ``supersample`` x ``supersample`` rays, averaged in linear light.

    Parameters
    ----------
    scene : SynthScene
    K : (3, 3) float64
        Camera matrix, pixels; pixel centres at integers.
    T_cam_table : (4, 4) float64
        Table (mm) to camera, the pose of this frame.
    size : (W, H)
        Image size, pixels.
    dist : (n,) array_like, optional
        OpenCV distortion ``k1, k2, p1, p2[, k3]``; the image shows what a lens
        with that distortion records (see the module docstring).
    supersample : int
        Rays per pixel along each axis at edges (1: no anti-aliasing).
    T_world_table : (4, 4) float64, optional
        Turntable rotation: table -> world (room) frame; identity by default.

    Returns
    -------
    rgb : (H, W, 3) uint8
        sRGB image.
    object_mask : (H, W) bool
        Pixels at least half covered by the object (at edges: by the fraction
        of sub-sample rays; elsewhere by the centre ray).
    """
    W, H = (int(v) for v in size)
    if W < 1 or H < 1:
        raise ValueError(f"image size must be positive, got {size}")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    T_cam_table = np.asarray(T_cam_table, float)
    if T_cam_table.shape != (4, 4):
        raise ValueError(f"T_cam_table: expected (4, 4), got {T_cam_table.shape}")
    T_wt = np.eye(4) if T_world_table is None else np.asarray(T_world_table, float)
    T_table_cam = invert_T(T_cam_table)
    light_dirs = _light_dirs(scene, s * s)
    vv, uu = np.mgrid[0:H, 0:W]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    lin, cover, cls = _render_pixels(scene, K, dist, uv, 1, T_table_cam, T_wt, light_dirs[:1])
    if s > 1:
        redo = np.flatnonzero(_needs_aa(cls.reshape(H, W), _encode_srgb(lin).reshape(H, W, 3) / 255.0))
        lin[redo], cover[redo], _ = _render_pixels(scene, K, dist, uv[redo], s, T_table_cam, T_wt, light_dirs)
    return _encode_srgb(lin).reshape(H, W, 3), (cover >= 0.5).reshape(H, W)
