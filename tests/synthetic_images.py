"""Synthetic photos of the two-ring target with known ground truth (test helper).

The printed sheet (``turntable.pattern.render_target_image``) is warped into the
camera through the plane homography ``H = K [r1 r3 t]`` (``calib.camera``),
supersampled ``S`` times and area-downsampled, composited on a backdrop, partly
hidden by an object standing on the target (a shaded frustum rising from the
pattern centre), then degraded: blur, uneven light, Gaussian noise, JPEG.

Raster layout of the sheet (``turntable.pattern``): pixel (row i, column j) has
its centre at table ``X = (j - c) / ppm``, ``Z = (i - c) / ppm``, ``c = (N - 1) / 2``,
so sheet pixel ``(j, i, 1)`` maps to table ``(X, Z, 1)`` by ``A = [[1/ppm, 0, -c/ppm],
[0, 1/ppm, -c/ppm], [0, 0, 1]]`` and to the image by ``H A``.

Ground truth of a ring edge of radius ``r``: ``calib.camera.circle_conic(K, T, r)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.camera import circle_points_table, look_at, make_T, plane_homography, project_points
from calib.target import TargetSpec
from turntable.pattern import render_target_image

__all__ = ["SyntheticPhoto", "look_at_T", "turntable_ring", "render_target_photo", "paper_raster", "sheet_size_mm"]


@dataclass(frozen=True)
class SyntheticPhoto:
    """A rendered photo and what is known about it.

    Attributes
    ----------
    image : (H, W, 3) uint8
        BGR photo.
    K : (3, 3) float64
    T_cam_table : (4, 4) float64
    occluder_mask : (H, W) bool
        Pixels covered by the object (empty when no occluder).
    """

    image: np.ndarray
    K: np.ndarray
    T_cam_table: np.ndarray
    occluder_mask: np.ndarray


def look_at_T(elevation_deg: float, azimuth_deg: float, distance_mm: float,
              look_at_table=(0.0, 0.0, 0.0), roll_deg: float = 0.0) -> np.ndarray:
    """``T_cam_table`` of a camera ``distance_mm`` from ``look_at_table``, elevated
    ``elevation_deg`` above the table plane, image rows pointing down the table's +Y."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    L = np.asarray(look_at_table, float)
    C = L + distance_mm * np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])
    z = (L - C) / np.linalg.norm(L - C)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_table_cam = np.column_stack([x, y, z])
    r = np.radians(roll_deg)
    Rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1.0]])
    R_cam_table = Rz @ R_table_cam.T
    return make_T(R_cam_table, -R_cam_table @ C)


def turntable_ring(n_views: int, look_y_mm: float, distance_mm: float = 450.0,
                   elevation_deg: float = 30.0) -> np.ndarray:
    """(n_views, 4, 4) ``T_cam_table`` of cameras evenly round the table's axis, ``distance_mm`` from the table
    origin and ``elevation_deg`` above its plane, each looking at the point ``look_y_mm`` up the axis."""
    e = np.radians(elevation_deg)
    out = []
    for th in np.linspace(0.0, 2.0 * np.pi, n_views, endpoint=False):
        c = distance_mm * np.array([np.cos(th) * np.cos(e), np.sin(e), np.sin(th) * np.cos(e)])
        out.append(look_at(c, np.array([0.0, look_y_mm, 0.0])))
    return np.array(out)


def paper_raster(spec: TargetSpec, px_per_mm: float, *, rings_mm=None,
                 size_mm: float | None = None) -> np.ndarray:
    """Sheet raster (N, N) uint8, white 255 / ink 0, in ``turntable.pattern``'s layout.

    The spec's rings and angle marks (``turntable.pattern``), or, with
    ``rings_mm``, a list of ``(x_mm, z_mm, radius_mm)`` rings (stroke
    ``spec.stroke_mm``, no marks) for bad-target tests.
    """
    if size_mm is None:
        size_mm = sheet_size_mm(spec)
    if rings_mm is None:
        img = render_target_image(spec, px_per_mm, size_mm=size_mm, supersample=2)
    else:
        img = _rings_raster(rings_mm, spec.stroke_mm, px_per_mm, size_mm)
    return img


def sheet_size_mm(spec: TargetSpec) -> float:
    """Side of the square sheet raster, mm (``turntable.pattern``'s default)."""
    return 2.0 * max(spec.r_outer_mm + 25.0, spec.extent_mm + 7.0)


def _rings_raster(rings_mm, stroke_mm: float, px_per_mm: float, size_mm: float) -> np.ndarray:
    n = int(round(size_mm * px_per_mm))
    s = 2
    c = (n - 1) / 2.0
    offs = (np.arange(s) + 0.5) / s - 0.5
    coords = ((np.arange(n)[:, None] + offs[None, :]).ravel() - c) / px_per_mm
    X, Z = np.meshgrid(coords, coords, indexing="xy")
    ink = np.zeros(X.shape, bool)
    for x0, z0, R in rings_mm:
        ink |= np.abs(np.hypot(X - x0, Z - z0) - R) <= stroke_mm / 2.0
    white = (~ink).astype(np.float32).reshape(n, s, n, s).mean(axis=(1, 3))
    return np.round(white * 255.0).astype(np.uint8)


def _backdrop(kind: str, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """Backdrop (h, w, 3) float32 in [0, 255]."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = {"dark": 30.0, "light": 185.0, "clutter": 110.0}.get(kind)
    if base is None:
        raise ValueError(f"backdrop must be 'dark', 'light' or 'clutter', got {kind!r}")
    tint = rng.uniform(0.7, 1.3, size=3).astype(np.float32)
    slow = 0.15 * np.sin(xx / w * rng.uniform(2, 6) + rng.uniform(0, 6)) * np.cos(yy / h * rng.uniform(2, 6))
    img = (base * (1.0 + slow))[..., None] * tint[None, None, :]
    img = np.ascontiguousarray(np.clip(img, 0, 255).astype(np.float32))
    if kind == "clutter":
        d = max(h, w)
        for _ in range(40):
            col = tuple(float(v) for v in rng.uniform(0, 255, 3))
            k = rng.integers(4)
            p = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
            if k == 0:
                q = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
                cv2.line(img, p, q, col, int(rng.integers(1, max(2, d // 150))), cv2.LINE_AA)
            elif k == 1:
                sz = (int(rng.uniform(d / 40, d / 6)), int(rng.uniform(d / 40, d / 6)))
                cv2.ellipse(img, p, sz, float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA)
            elif k == 2:
                sz = (int(rng.uniform(d / 30, d / 8)), int(rng.uniform(d / 30, d / 8)))
                cv2.ellipse(img, p, sz, float(rng.uniform(0, 180)), 0, 360, col,
                            int(rng.integers(1, max(2, d // 100))), cv2.LINE_AA)
            else:
                q = (p[0] + int(rng.uniform(-d / 6, d / 6)), p[1] + int(rng.uniform(-d / 6, d / 6)))
                cv2.rectangle(img, p, q, col, -1)
    return img


def _occluder_polygon(spec: TargetSpec, K, T, rng: np.random.Generator,
                      max_hidden: float) -> np.ndarray:
    """Image outline (M, 2), pixels, of a frustum standing on the pattern centre.

    The frustum shrinks until it hides at most ``max_hidden`` of either ring.
    """
    rb = rng.uniform(0.45, 0.6) * spec.r_inner_mm
    rt = rng.uniform(0.75, 0.95) * spec.r_outer_mm
    hgt = rng.uniform(1.2, 1.6) * spec.r_outer_mm
    th = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rings = [project_points(K, T, circle_points_table(r, 360)) for r in (spec.r_outer_mm, spec.r_inner_mm)]
    for _ in range(30):
        bottom = np.column_stack([rb * np.cos(th), np.zeros_like(th), rb * np.sin(th)])
        top = np.column_stack([rt * np.cos(th), np.full_like(th, hgt), rt * np.sin(th)])
        uv = project_points(K, T, np.vstack([bottom, top]))
        hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
        hidden = max(np.mean([cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in ring])
                     for ring in rings)
        if hidden <= max_hidden:
            break
        rt, hgt = max(rb, 0.85 * rt), 0.85 * hgt
    return hull


def render_target_photo(spec: TargetSpec, K, T_cam_table, size, *, rng: np.random.Generator,
                        occluder: bool = True, backdrop: str = "dark", blur_px: float = 0.7,
                        noise_sigma: float = 2.0, jpeg_quality: int | None = 90,
                        gain_gradient: float = 0.3,
                        rings_mm=None, supersample: int = 2,
                        max_hidden: float = 0.4, gamma: float = 2.2) -> SyntheticPhoto:
    """Render a photo of the target seen by ``K``, ``T_cam_table``.

    Parameters
    ----------
    spec : TargetSpec
    K : (3, 3) array_like, pixels
    T_cam_table : (4, 4) array_like, mm
    size : (width, height) in pixels
    rng : numpy Generator (backdrop, occluder, noise)
    occluder : draw an object standing on the target, hiding the far side of the rings
    backdrop : "dark", "light" or "clutter"
    blur_px : Gaussian blur sigma in pixels (0: none)
    noise_sigma : Gaussian noise sigma in grey levels
    jpeg_quality : JPEG round trip quality, None for none
    gain_gradient : relative light fall-off across the frame (0: even light)
    rings_mm : optional ``(x_mm, z_mm, radius_mm)`` rings drawn instead of the spec's
    supersample : S, rendering at S times the resolution before area-downsampling
    max_hidden : the occluder hides at most this fraction of either ring
    gamma : encoding gamma; levels, backdrop and object colours are encoded values,
        the optics (pixel area, blur, light fall-off) act in linear light, then
        the image is encoded ``I = 255 (L / 255)^(1 / gamma)`` as cameras do
    """
    K = np.asarray(K, float)
    T = np.asarray(T_cam_table, float)
    w, h = int(size[0]), int(size[1])
    S = int(supersample)
    H = plane_homography(K, T)
    # sheet resolution ~ the finest image scale of the sheet, times S
    size_mm = sheet_size_mm(spec)
    half = size_mm / 2.0
    g = np.linspace(-half, half, 9)
    Xg, Zg = np.meshgrid(g, g)
    pts = np.column_stack([Xg.ravel(), np.zeros(Xg.size), Zg.ravel()])
    depth = (pts @ T[:3, :3].T + T[:3, 3])[:, 2]
    if np.any(depth <= 0):
        raise ValueError("the sheet is not fully in front of the camera")
    px_per_mm_img = float(np.max(K[0, 0] / depth))
    ppm = float(np.clip(px_per_mm_img * S * 1.2, 2.0, 2000.0 / size_mm))
    sheet = paper_raster(spec, ppm, rings_mm=rings_mm, size_mm=size_mm)
    n = sheet.shape[0]
    c = (n - 1) / 2.0
    A = np.array([[1 / ppm, 0, -c / ppm], [0, 1 / ppm, -c / ppm], [0, 0, 1.0]])
    # supersampled image pixel u_s = S u + (S - 1) / 2
    U = np.array([[S, 0, (S - 1) / 2.0], [0, S, (S - 1) / 2.0], [0, 0, 1.0]])
    M = U @ H @ A
    Ws, Hs = w * S, h * S
    paper_level = rng.uniform(215, 245)
    ink_level = rng.uniform(15, 40)
    lin = (lambda v: 255.0 * np.power(np.clip(v, 0, 255) / 255.0, gamma))  # noqa: E731  encoded -> linear
    sheet_f = lin(ink_level) + (lin(paper_level) - lin(ink_level)) * (sheet.astype(np.float32) / 255.0)
    warped = cv2.warpPerspective(sheet_f, M, (Ws, Hs), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    alpha = cv2.warpPerspective(np.ones((n, n), np.float32), M, (Ws, Hs), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    back = lin(cv2.resize(_backdrop(backdrop, h, w, rng), (Ws, Hs), interpolation=cv2.INTER_LINEAR))
    img = back * (1.0 - alpha[..., None]) + warped[..., None] * alpha[..., None]
    occ = np.zeros((Hs, Ws), np.uint8)
    if occluder:
        poly = (_occluder_polygon(spec, K, T, rng, max_hidden) + 0.5) * S - 0.5
        cv2.fillPoly(occ, [np.round(poly * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
        col = rng.uniform(20, 230, 3).astype(np.float32)
        u0, u1 = poly[:, 0].min(), poly[:, 0].max()
        shade = 0.55 + 0.45 * np.sin(np.clip((np.arange(Ws) - u0) / max(u1 - u0, 1.0), 0, 1) * np.pi)
        obj = lin(shade[None, :, None].astype(np.float32) * col[None, None, :])
        a = (occ.astype(np.float32) / 255.0)[..., None]
        img = img * (1.0 - a) + obj * a
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    occ_mask = cv2.resize(occ, (w, h), interpolation=cv2.INTER_AREA) > 0
    if gain_gradient > 0:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        ang = rng.uniform(0, 2 * np.pi)
        ramp = (np.cos(ang) * (xx / w - 0.5) + np.sin(ang) * (yy / h - 0.5))
        gain = 1.0 - gain_gradient * (ramp + 0.5)
        img = img * gain[..., None]
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = 255.0 * np.power(np.clip(img, 0, 255) / 255.0, 1.0 / gamma)  # linear light -> encoded
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return SyntheticPhoto(image=out, K=K, T_cam_table=T, occluder_mask=occ_mask)


SEAT_LO, SEAT_HI = np.array([-27.0, 45.0, -27.0]), np.array([27.0, 51.0, 27.0])  # a stool's seat, 6 mm thick,
STOOL = [(SEAT_LO, SEAT_HI)] + [(np.array([x - 2.5, 0.0, z - 2.5]), np.array([x + 2.5, 45.0, z + 2.5]))
                               for x in (-24.5, 24.5) for z in (-24.5, 24.5)]  # ... on four legs at its corners


def box_hit(o, d, lo, hi):
    """Distance along each ray (origin ``o``, unit directions ``d`` (N, 3)) to the box (``lo``, ``hi``), and the
    normal there (inf where it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    near, far = np.minimum(t0, t1), np.maximum(t0, t1)
    t_in, t_out = near.max(1), far.min(1)
    hit = (t_in <= t_out) & (t_out > 0)
    axis = near.argmax(1)
    n = np.zeros_like(d)
    n[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    return np.where(hit, t_in, np.inf), n


def boxes_hit(o, d, boxes):
    """Distance along each ray to the nearest of the boxes (lo, hi), and the normal there."""
    t, n = np.full(len(d), np.inf), np.zeros_like(d)
    for lo, hi in boxes:
        tb, nb = box_hit(o, d, lo, hi)
        nearer = tb < t
        t, n[nearer] = np.where(nearer, tb, t), nb[nearer]
    return t, n


def hull_holds(hull, pts: np.ndarray) -> np.ndarray:
    """(N,) bool: the points' voxels are inside the hull (``recon.types.VoxelHull``; False off its grid)."""
    idx = np.rint((pts - hull.origin_table) / hull.voxel_mm).astype(int)
    on = ((idx >= 0) & (idx < hull.values.shape)).all(1)
    out = np.zeros(len(pts), bool)
    out[on] = hull.values[idx[on, 0], idx[on, 1], idx[on, 2]] > 0
    return out
