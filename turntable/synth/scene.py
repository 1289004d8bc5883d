"""The synthetic turntable scene: geometry for the ray caster, textures, light.

Two ray-casting scenes make up a view. The *turntable* scene lives in the table
frame and turns with the turntable: the object and the turntable disc (a
15 mm thick cylinder whose top face is the plane Y = 0, carrying the printed
paper target). The *room* scene lives in the world frame, which is the table
frame at turntable angle 0: the table top beyond the disc (Y = -15 mm), a round
wall 700 mm from the centre and, optionally, a flat backdrop behind the
turntable. Textures are rasters of linear-light albedo sampled bilinearly; the
object's albedo is its procedural texture evaluated at the hit point (or its
interpolated vertex colours).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
import trimesh

from calib.target import TargetSpec
from turntable.pattern import render_target_image

__all__ = ["SynthScene", "build_scene", "BACKDROPS", "DISC_THICKNESS_MM", "ROOM_HEIGHT_MM", "WALL_MM_PER_PX",
           "gamma22_to_linear"]

BACKDROPS = ("dark", "light", "colour", "clutter")

DISC_THICKNESS_MM = 15.0
_ROOM_RADIUS_MM = 700.0  # default radius of the round wall
ROOM_HEIGHT_MM = 2000.0
WALL_MM_PER_PX = 2.0


@dataclass(frozen=True)
class SynthScene:
    """What :func:`render_view` needs: ray-casting scenes and shading inputs.

    Attributes
    ----------
    turntable, room : open3d.t.geometry.RaycastingScene
        Geometry in the table frame (object, disc) and in the world frame
        (table top, wall).
    object_id, disc_id, floor_id, wall_id, backdrop_id : int
        Geometry ids returned by the ray caster (``backdrop_id`` -1: no flat
        backdrop, only the round wall).
    vertices_table : (N, 3) float32
        Object vertices, mm; ``faces`` (M, 3) int64; ``vertex_normals`` (N, 3)
        float32 and ``face_normals`` (M, 3) float32, unit; ``vertex_rgb`` (N, 3)
        float32 sRGB in [0, 1].
    albedo : callable or None
        Procedural texture ``(K, 3) table points -> (K, 3) sRGB in [0, 1]``;
        None: interpolate ``vertex_rgb``.
    disc_top_linear : (P, P, 3) float32
        Linear-light albedo of the disc's top face (the paper target cut to a
        disc of ``paper_radius_mm`` on the turntable's colour); pixel (i, j) has
        its centre at ``X = (j - c) / disc_top_px_per_mm``, ``Z = (i - c) /
        disc_top_px_per_mm``, ``c = (P - 1) / 2`` -- the layout of
        :func:`turntable.pattern.render_target_image`, so the printed 0 deg
        mark lies on the table's +X axis whatever the turntable angle.
    disc_side_linear : (3,) float32
        Linear albedo of the disc's rim.
    floor_linear : (Q, Q, 3) float32
        Linear albedo of the table top (world frame, same layout as the disc,
        ``floor_px_per_mm``); ``wall_linear`` (h, w, 3) float32 the wall,
        unwrapped by azimuth (columns) and height (rows, 0 at the top).
    light_dir_world : (3,) float64
        Unit vector towards the light.
    """

    turntable: o3d.t.geometry.RaycastingScene
    room: o3d.t.geometry.RaycastingScene
    object_id: int
    disc_id: int
    floor_id: int
    wall_id: int
    backdrop_id: int
    vertices_table: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    face_normals: np.ndarray
    vertex_rgb: np.ndarray
    albedo: Callable[[np.ndarray], np.ndarray] | None
    disc_top_linear: np.ndarray
    disc_top_px_per_mm: float
    disc_side_linear: np.ndarray
    floor_linear: np.ndarray
    floor_px_per_mm: float
    wall_linear: np.ndarray
    paper_radius_mm: float
    disc_radius_mm: float
    light_dir_world: np.ndarray
    light_cone_rad: float = 0.04
    ambient: float = 0.3
    diffuse: float = 0.75
    specular: float = 0.08
    shininess: float = 40.0


# --------------------------------------------------------------------------- scene
def _cylinder(radius: float, y0: float, y1: float, n: int, caps: bool) -> tuple[np.ndarray, np.ndarray]:
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([radius * np.cos(th), np.zeros(n), radius * np.sin(th)])
    lo, hi = ring + [0, y0, 0], ring + [0, y1, 0]
    V = np.vstack([lo, hi, [[0, y0, 0], [0, y1, 0]]])
    j, jn = np.arange(n), (np.arange(n) + 1) % n
    F = [np.column_stack([j, n + jn, jn]), np.column_stack([j, n + j, n + jn])]
    if caps:
        F += [np.column_stack([np.full(n, 2 * n), jn, j]), np.column_stack([np.full(n, 2 * n + 1), n + j, n + jn])]
    return V.astype(np.float32), np.vstack(F).astype(np.uint32)


def _wall_image(backdrop: str, rng: np.random.Generator) -> np.ndarray:
    """Display-encoded (gamma 2.2) wall texture (h, w, 3) float32, ``WALL_MM_PER_PX`` mm a pixel, unwrapped cylinder."""
    h, w = int(ROOM_HEIGHT_MM / WALL_MM_PER_PX), int(2 * np.pi * _ROOM_RADIUS_MM / WALL_MM_PER_PX)
    noise = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 6.0)
    if backdrop == "dark":
        base = np.array([0.07, 0.07, 0.075])
    elif backdrop == "light":
        base = np.array([0.78, 0.77, 0.74])
    elif backdrop == "colour":
        base = np.array([[0.1, 0.35, 0.6], [0.15, 0.5, 0.25], [0.6, 0.2, 0.15], [0.55, 0.45, 0.1]])[rng.integers(4)]
    elif backdrop == "clutter":  # shelves, boxes, posters, cables: many edges of every contrast
        img = np.full((h, w, 3), 0.45, np.float32) * rng.uniform(0.5, 1.2, 3).astype(np.float32)
        for _ in range(1500):
            c = tuple(float(x) for x in rng.uniform(0.02, 0.95, 3))
            x, y = int(rng.integers(w)), int(rng.integers(h))
            sx, sy = (int(v) for v in rng.integers(4, 50, 2))
            if rng.random() < 0.6:
                cv2.rectangle(img, (x, y), (x + sx, y + sy), c, -1)
            else:
                cv2.circle(img, (x, y), int(sx) // 2, c, -1, cv2.LINE_AA)
        for _ in range(150):  # thin lines: shelf edges, cables
            c = tuple(float(x) for x in rng.uniform(0.0, 1.0, 3))
            p0, p1 = rng.integers(0, [w, h], 2), rng.integers(0, [w, h], 2)
            cv2.line(img, tuple(int(v) for v in p0), tuple(int(v) for v in p1), c, int(rng.integers(1, 5)),
                     cv2.LINE_AA)
        fine = _blur_noise(rng, (h, w), 1.0)
        return np.clip(img * (1.0 + 0.08 * noise[..., None] + 0.05 * fine[..., None]), 0, 1).astype(np.float32)
    else:
        raise ValueError(f"unknown backdrop {backdrop!r}; choose one of {', '.join(BACKDROPS)}")
    img = base[None, None, :] * (1.0 + 0.06 * noise[..., None])
    return np.clip(img, 0, 1).astype(np.float32)


def gamma22_to_linear(x: np.ndarray) -> np.ndarray:
    """Display values in [0, 1] (clipped) -> linear light by a pure power 2.2, float32.

    The renderer's own transfer curve (its inverse encodes the images), not the
    piecewise IEC 61966-2-1 sRGB curve of :func:`recon.export.srgb_to_linear`:
    the two differ by up to 0.0085 (near 0.75), and the rendered pixels depend
    on this one.
    """
    return np.power(np.clip(x, 0.0, 1.0), 2.2).astype(np.float32)


def _blur_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-std smooth noise (float32) of correlation length ``sigma_px``.

    Wide kernels are blurred at a reduced resolution and resized up (cheap).
    """
    h, w = shape
    f = max(1.0, sigma_px / 2.0)
    small = (max(2, int(np.ceil(h / f)) + 2), max(2, int(np.ceil(w / f)) + 2))
    n = cv2.GaussianBlur(rng.standard_normal(small).astype(np.float32), (0, 0), sigma_px / f)
    if f > 1.0:
        n = cv2.resize(n, (int(round(small[1] * f)), int(round(small[0] * f))), interpolation=cv2.INTER_CUBIC)
    n = np.ascontiguousarray(n[:h, :w])
    return (n - n.mean()) / max(float(n.std()), 1e-12)


def _paper_radius_mm(spec: TargetSpec) -> float:
    """Radius of the paper disc: the target raster's default half-side."""
    extent = float(getattr(spec, "extent_mm", spec.r_outer_mm))
    return max(spec.r_outer_mm + 25.0, extent + 7.0)


def _disc_top_texture(spec: TargetSpec, px_per_mm: float, paper_r: float, disc_r: float,
                      rng: np.random.Generator, ground_rgb=(255, 255, 255)) -> np.ndarray:
    """Linear albedo raster of the disc top: paper target on a slightly grainy disc.

    ``ground_rgb`` (sRGB 0-255) is the printed ground under the ink: it filters
    the slightly warm paper (white: the bare paper); the ink stays black.
    """
    try:
        target = render_target_image(spec, px_per_mm, supersample=2)
    except TypeError:  # a signature without supersample
        target = render_target_image(spec, px_per_mm)
    target = np.asarray(target, dtype=np.float32)
    if target.ndim == 3:
        target = target[..., :3].mean(axis=2)
    n = target.shape[0]
    m = max(int(np.ceil(disc_r * px_per_mm - (n - 1) / 2.0)) + 2, 0)
    size = n + 2 * m  # same parity as n: pixel centres line up with the target's
    c = (size - 1) / 2.0
    paper_r = min(paper_r, (n - 1) / 2.0 / px_per_mm)
    ax = (np.arange(size, dtype=np.float32) - c) / px_per_mm
    r = np.hypot(ax[None, :], ax[:, None])
    disc_rgb = np.clip(np.array([0.32, 0.3, 0.33]) * rng.uniform(0.8, 1.1, 3), 0, 1)
    grain = 1.0 + 0.07 * _blur_noise(rng, (size, size), 0.8 * px_per_mm)
    img = grain[..., None] * disc_rgb[None, None, :].astype(np.float32)
    paper = np.full((size, size), 255.0, np.float32)
    paper[m:m + n, m:m + n] = target
    fibre = 1.0 + 0.006 * _blur_noise(rng, (size, size), 0.5 * px_per_mm)
    ground = np.array([1.0, 0.99, 0.96], np.float32) * (np.asarray(ground_rgb, np.float32) / 255.0)
    paper_rgb = (paper * fibre / 255.0 * 0.92)[..., None] * ground
    alpha = np.clip((paper_r - r) * px_per_mm + 0.5, 0.0, 1.0)[..., None]
    return gamma22_to_linear(alpha * paper_rgb + (1.0 - alpha) * img)


def _floor_texture(rng: np.random.Generator, half_mm: float, px_per_mm: float) -> np.ndarray:
    """Linear albedo raster of a wood-grained table top (layout as the disc's)."""
    size = int(2 * half_mm * px_per_mm) + 1
    z = (np.arange(size, dtype=np.float32) - (size - 1) / 2.0) / px_per_mm
    warp = _blur_noise(rng, (size, size), 12.0 * px_per_mm)
    grain = 0.5 + 0.5 * np.sin(z[:, None] / 2.5 + 1.2 * warp)
    base = np.clip(np.array([0.55, 0.4, 0.27]) * rng.uniform(0.8, 1.15, 3), 0, 1).astype(np.float32)
    return gamma22_to_linear((0.8 + 0.2 * grain)[..., None] * base)


def build_scene(mesh: trimesh.Trimesh, spec: TargetSpec, backdrop: str = "dark", *,
                rng: np.random.Generator, target_px_per_mm: float = 6.0,
                backdrop_distance_mm: float | None = None, room_radius_mm: float = _ROOM_RADIUS_MM,
                light_dir_world=(-0.45, 1.0, 0.55), target_background=(255, 255, 255)) -> SynthScene:
    """Assemble the turntable and room ray-casting scenes around ``mesh``.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Object in the table frame (mm), vertex colours; a
        ``mesh.metadata["albedo"]`` texture is used when present.
    spec : TargetSpec
        Printed rings and angle marks; the paper is a disc of radius
        ``max(r_outer + 25, marks' outer radius + 7)`` mm cut from the raster of
        :func:`turntable.pattern.render_target_image`; the turntable disc has
        radius ``r_outer + 40`` mm (at least 12 mm more than the paper) and is
        15 mm thick.
    backdrop : {"dark", "light", "colour", "clutter"}
    rng : numpy.random.Generator
        Draws the disc, table and wall colours and textures.
    target_px_per_mm : float
        Resolution of the disc-top raster (keep it >= 2 per image pixel).
    backdrop_distance_mm : float, optional
        Puts a flat backdrop (the wall texture) in the world plane
        ``Z = -backdrop_distance_mm``, behind the turntable for a camera on
        the +Z side; without it only the round wall surrounds the table
        (hand-held sequences look from every side).
    room_radius_mm : float
        Radius of the round wall; every camera must stand inside it.
    light_dir_world : (3,) array_like
        Direction towards the light, world frame (normalised here).
    target_background : (3,) int
        sRGB 0-255 ground colour printed under the target's ink (``turntable
        pattern --background``); white: plain paper.
    """
    if backdrop not in BACKDROPS:
        raise ValueError(f"unknown backdrop {backdrop!r}; choose one of {', '.join(BACKDROPS)}")
    paper_r = _paper_radius_mm(spec)
    disc_r = max(spec.r_outer_mm + 40.0, paper_r + 12.0)
    disc_top = _disc_top_texture(spec, target_px_per_mm, paper_r, disc_r, rng, target_background)

    tt = o3d.t.geometry.RaycastingScene()
    V = np.asarray(mesh.vertices, np.float32)
    F = np.asarray(mesh.faces, np.int64)
    object_id = tt.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))
    dv, df = _cylinder(disc_r, -DISC_THICKNESS_MM, 0.0, 256, caps=True)
    disc_id = tt.add_triangles(o3d.core.Tensor(dv), o3d.core.Tensor(df))

    room = o3d.t.geometry.RaycastingScene()
    if not room_radius_mm > disc_r + 50.0:
        raise ValueError(f"room radius {room_radius_mm} mm leaves no room around the turntable")
    R = room_radius_mm * 1.2
    fv = np.array([[-R, -DISC_THICKNESS_MM, -R], [R, -DISC_THICKNESS_MM, -R], [R, -DISC_THICKNESS_MM, R],
                   [-R, -DISC_THICKNESS_MM, R]], np.float32)
    floor_id = room.add_triangles(o3d.core.Tensor(fv), o3d.core.Tensor(np.array([[0, 2, 1], [0, 3, 2]], np.uint32)))
    wv, wf = _cylinder(room_radius_mm, -DISC_THICKNESS_MM - 1.0, ROOM_HEIGHT_MM, 512, caps=False)
    wall_id = room.add_triangles(o3d.core.Tensor(wv), o3d.core.Tensor(wf))
    backdrop_id = -1
    if backdrop_distance_mm is not None:
        zb = -float(backdrop_distance_mm)
        bv = np.array([[-R, -DISC_THICKNESS_MM - 1.0, zb], [R, -DISC_THICKNESS_MM - 1.0, zb],
                       [R, ROOM_HEIGHT_MM, zb], [-R, ROOM_HEIGHT_MM, zb]], np.float32)
        backdrop_id = int(room.add_triangles(o3d.core.Tensor(bv),
                                             o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32))))

    tm = trimesh.Trimesh(V, F, process=False)
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3] if mesh.visual.kind == "vertex" else np.full((len(V), 3), 180)
    light = np.asarray(light_dir_world, float)
    side = gamma22_to_linear(np.array([0.25, 0.24, 0.26]) * rng.uniform(0.8, 1.1, 3))
    floor_ppm = min(1.0, 2000.0 / (2.0 * R))  # at most a 2000^2 raster
    return SynthScene(
        turntable=tt, room=room, object_id=int(object_id), disc_id=int(disc_id), floor_id=int(floor_id),
        wall_id=int(wall_id), backdrop_id=backdrop_id, vertices_table=V, faces=F,
        vertex_normals=np.asarray(tm.vertex_normals, np.float32), face_normals=np.asarray(tm.face_normals, np.float32),
        vertex_rgb=(colors / 255.0).astype(np.float32), albedo=mesh.metadata.get("albedo"),
        disc_top_linear=disc_top, disc_top_px_per_mm=float(target_px_per_mm), disc_side_linear=side,
        floor_linear=_floor_texture(rng, R, floor_ppm), floor_px_per_mm=floor_ppm,
        wall_linear=gamma22_to_linear(_wall_image(backdrop, rng)), paper_radius_mm=float(paper_r),
        disc_radius_mm=float(disc_r), light_dir_world=light / np.linalg.norm(light))
